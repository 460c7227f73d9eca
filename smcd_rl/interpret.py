"""What inferred masks say about their context: k-nearest-mask confidence and neighbour accuracy.

Exported names:

* :func:`confidence_score`: the distance-based confidence of eq. (9) (paper section 4.3), the
  share of the ``k`` nearest stored masks' weight ``exp(-distance)`` that carries a label.
* :func:`nearest_masks`: the ``k`` nearest stored masks and their Euclidean distances, on which
  :func:`confidence_score` is built.
* :func:`top_k_neighbour_accuracy`: appendix A.5 / Fig. 9, how often the nearest neighbour in a
  property space (link lengths) is among the ``k`` nearest neighbours in mask space.

Masks are any float tensors ``[..., mask_dim]``: usually SMCD's MMSE masks (``model.mask``).

Example:
    >>> import torch
    >>> from smcd_rl.interpret import confidence_score
    >>> stored = torch.tensor([[0.0, 0.0], [0.1, 0.0], [1.0, 1.0]])
    >>> labels = torch.tensor([0, 0, 1])
    >>> confidence_score(torch.tensor([0.05, 0.0]), stored, labels, k=2, label=0)
    tensor(1.)
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["confidence_score", "nearest_masks", "top_k_neighbour_accuracy"]


def nearest_masks(query_masks: Tensor, train_masks: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The ``k`` stored masks nearest (Euclidean) to each query mask, nearest first.

    Args:
        query_masks: ``[Q, D]`` (or ``[D]`` for one query).
        train_masks: the stored set ``[M, D]``.
        k: neighbours per query, ``1 <= k <= M``.

    Returns:
        ``(distances [Q, k], indices [Q, k])`` (without the ``Q`` dim for a single query).

    Raises:
        ValueError: ``k`` out of range, or shapes that do not match.

    Example:
        >>> import torch
        >>> d, i = nearest_masks(torch.tensor([0.0, 0.0]), torch.tensor([[3.0, 4.0], [1.0, 0.0]]), k=2)
        >>> d, i
        (tensor([1., 5.]), tensor([1, 0]))
    """
    query, single = _check_masks(query_masks, train_masks)
    _check_k(k, train_masks.shape[0], "stored masks")
    distances = torch.cdist(query.to(train_masks.dtype), train_masks)
    values, indices = torch.topk(distances, int(k), dim=-1, largest=False, sorted=True)
    return (values[0], indices[0]) if single else (values, indices)


def confidence_score(
    query_masks: Tensor,
    train_masks: Tensor,
    train_labels: Tensor,
    k: int,
    label: Tensor | int | None = None,
) -> Tensor:
    """Eq. (9): confidence of assigning a label to each query mask, from its ``k`` nearest stored masks.

    With ``A`` the ``k`` stored masks nearest to the query ``m`` and ``c_j`` their labels:

        D = sum_{j in A, c_j = label} exp(-|m - m_j|) / sum_{j in A} exp(-|m - m_j|)

    ``D`` lies in ``[0, 1]``: 1 when all ``k`` neighbours carry the label, 0 when none does,
    strictly between otherwise. It is computed as a softmax of the negative distances, which is
    the same quantity but does not underflow to 0/0 when every distance is large.

    Args:
        query_masks: ``[Q, D]`` masks to score (or ``[D]`` for one).
        train_masks: the stored masks ``[M, D]``.
        train_labels: integer labels of the stored masks ``[M]``.
        k: neighbours, ``1 <= k <= M`` (the paper uses 5).
        label: the assigned label per query (``[Q]`` or one int for all), e.g. the true label.
            ``None`` scores the label the neighbours themselves assign: the one with the largest
            summed weight (the k-NN prediction's own confidence).

    Returns:
        ``[Q]`` confidences (a 0-d tensor for a single query).

    Raises:
        ValueError: ``k`` out of range, shapes that do not match, non-integer labels.

    Example:
        >>> import torch, math
        >>> stored = torch.tensor([[0.0], [1.0], [2.0]])
        >>> labels = torch.tensor([1, 0, 1])
        >>> d = confidence_score(torch.tensor([[0.0]]), stored, labels, k=2, label=1)
        >>> bool(torch.isclose(d, torch.tensor([1 / (1 + math.exp(-1))])))
        True
    """
    query, single = _check_masks(query_masks, train_masks)
    labels = torch.as_tensor(train_labels, device=train_masks.device)
    if labels.dim() != 1 or labels.shape[0] != train_masks.shape[0]:
        raise ValueError(
            f"train_labels must be [{train_masks.shape[0]}] (one per stored mask), got {list(labels.shape)}"
        )
    if labels.is_floating_point() or labels.dtype == torch.bool:
        raise ValueError(f"train_labels must be integer class indices, got dtype {labels.dtype}")
    distances, indices = nearest_masks(query, train_masks, k)
    weights = torch.softmax(-distances, dim=-1)  # [Q, k]
    neighbour_labels = labels[indices]  # [Q, k]
    if label is None:
        classes = int(labels.max()) + 1 if labels.numel() else 1
        per_class = torch.zeros(query.shape[0], classes, dtype=weights.dtype, device=weights.device)
        per_class.scatter_add_(1, neighbour_labels, weights)
        score = per_class.max(-1).values
    else:
        assigned = torch.as_tensor(label, device=train_masks.device)
        if assigned.is_floating_point() or assigned.dtype == torch.bool:
            raise ValueError(f"label must be integer class indices, got dtype {assigned.dtype}")
        if assigned.dim() > 1 or (assigned.dim() == 1 and assigned.shape[0] != query.shape[0]):
            raise ValueError(f"label must be one int or [{query.shape[0]}] (one per query), got {list(assigned.shape)}")
        assigned = assigned.expand(query.shape[0])
        score = (weights * (neighbour_labels == assigned.unsqueeze(-1))).sum(-1)
    return score[0] if single else score


def top_k_neighbour_accuracy(masks: Tensor, properties: Tensor, ks: Sequence[int]) -> Tensor:
    """Appendix A.5: how often the nearest neighbour in property space is among the k nearest in mask space.

    For every item ``i`` of the set, its nearest other item in property space (e.g. link lengths)
    is found; a hit at ``k`` means that item is among ``i``'s ``k`` nearest other items in mask
    space (ties in mask distance count as hits). Chance level (masks unrelated to properties) is
    ``k / (n - 1)``.

    Args:
        masks: ``[n, mask_dim]``, one inferred mask per item.
        properties: ``[n, p]`` the property the masks should encode (e.g. link lengths).
        ks: the ``k`` values, each ``1 <= k <= n - 1``.

    Returns:
        ``[len(ks)]`` accuracies in ``[0, 1]``.

    Raises:
        ValueError: fewer than 2 items, mismatched lengths, or a ``k`` out of range.

    Example:
        >>> import torch
        >>> lengths = torch.tensor([[1.0], [1.1], [3.0], [3.2]])
        >>> masks = torch.tensor([[0.0], [0.1], [5.0], [5.1]])  # the same neighbourhoods
        >>> top_k_neighbour_accuracy(masks, lengths, ks=[1, 2])
        tensor([1., 1.])
    """
    if masks.dim() != 2 or properties.dim() != 2:
        raise ValueError(
            f"masks and properties must be 2-d [n, features], got {list(masks.shape)} and {list(properties.shape)}"
        )
    n = masks.shape[0]
    if properties.shape[0] != n:
        raise ValueError(f"masks has {n} items but properties has {properties.shape[0]}; one row per item in both")
    if n < 2:
        raise ValueError(f"need at least 2 items to find neighbours, got {n}")
    ks = list(ks)
    if not ks:
        raise ValueError("ks must list at least one k")
    for k in ks:
        _check_k(k, n - 1, "other items (n - 1)")  # refuses k = 2.5 rather than truncating it
    ks = [int(k) for k in ks]
    eye = torch.eye(n, dtype=torch.bool, device=masks.device)
    property_distance = torch.cdist(properties.double(), properties.double()).masked_fill(eye, float("inf"))
    nearest = property_distance.argmin(-1)  # [n]
    mask_distance = torch.cdist(masks.double(), masks.double()).masked_fill(eye, float("inf"))
    # Rank of the property neighbour among the mask neighbours: how many others are strictly closer.
    reference = mask_distance.gather(1, nearest.unsqueeze(-1))
    rank = (mask_distance < reference).sum(-1)
    return torch.stack([(rank < k).double().mean() for k in ks]).to(
        masks.dtype if masks.is_floating_point() else torch.float32
    )


def _check_masks(query_masks: Tensor, train_masks: Tensor) -> tuple[Tensor, bool]:
    if train_masks.dim() != 2:
        raise ValueError(f"train_masks must be [M, mask_dim], got {list(train_masks.shape)}")
    single = query_masks.dim() == 1
    query = query_masks.unsqueeze(0) if single else query_masks
    if query.dim() != 2 or query.shape[-1] != train_masks.shape[-1]:
        raise ValueError(
            f"query_masks must be [Q, {train_masks.shape[-1]}] or [{train_masks.shape[-1]}] to match train_masks "
            f"{list(train_masks.shape)}, got {list(query_masks.shape)}"
        )
    return query, single


def _check_k(k: int, available: int, what: str) -> None:
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")
    if k > available:
        raise ValueError(f"k = {k} but there are only {available} {what}; use k <= {available}")
