"""Eq. (9) confidence and the A.5 top-k neighbour accuracy (smcd_rl.interpret)."""

from __future__ import annotations

import math

import pytest
import torch

from smcd_rl.interpret import confidence_score, nearest_masks, top_k_neighbour_accuracy

STORED = torch.tensor([[0.0, 0.0], [3.0, 4.0], [1.0, 0.0], [0.0, 2.0], [10.0, 10.0]])
LABELS = torch.tensor([0, 1, 0, 1, 1])


def test_eq9_equals_the_hand_computed_value() -> None:
    # Query at the origin, k = 3: neighbours at distances 0 (label 0), 1 (label 0), 2 (label 1).
    total = 1 + math.exp(-1) + math.exp(-2)
    query = torch.tensor([0.0, 0.0])
    assert float(confidence_score(query, STORED, LABELS, k=3, label=0)) == pytest.approx((1 + math.exp(-1)) / total)
    assert float(confidence_score(query, STORED, LABELS, k=3, label=1)) == pytest.approx(math.exp(-2) / total)
    # Without a label: the neighbours' own assignment (label 0) and its confidence.
    assert float(confidence_score(query, STORED, LABELS, k=3)) == pytest.approx((1 + math.exp(-1)) / total)


def test_scores_of_all_labels_sum_to_one_and_lie_in_the_unit_interval() -> None:
    queries = torch.randn(50, 2, generator=torch.Generator().manual_seed(0)) * 3
    zero = confidence_score(queries, STORED, LABELS, k=4, label=0)
    one = confidence_score(queries, STORED, LABELS, k=4, label=torch.ones(50, dtype=torch.long))
    assert torch.allclose(zero + one, torch.ones(50))
    # With k = 4 both labels are always among the neighbours, so each score is strictly inside (0, 1).
    assert bool(((zero > 0) & (zero < 1)).all())


def test_a_label_all_or_none_of_the_neighbours_carry_scores_one_or_zero() -> None:
    query = torch.tensor([0.5, 0.0])
    assert float(confidence_score(query, STORED, LABELS, k=2, label=0)) == 1.0
    assert float(confidence_score(query, STORED, LABELS, k=2, label=1)) == 0.0
    assert float(confidence_score(query, STORED, LABELS, k=2, label=7)) == 0.0


def test_far_queries_do_not_underflow() -> None:
    """exp(-1000) is 0 in float32; eq. (9) is a ratio, so the score must still be defined."""
    far = torch.tensor([[1000.0, 1000.0]])
    score = confidence_score(far, STORED, LABELS, k=3, label=1)
    assert torch.isfinite(score).all() and 0.5 < float(score) <= 1.0  # the nearest, [10, 10], is label 1


def test_nearest_masks_orders_by_euclidean_distance() -> None:
    distances, indices = nearest_masks(torch.tensor([[0.0, 0.0]]), STORED, k=3)
    assert indices.tolist() == [[0, 2, 3]] and distances.tolist() == [[0.0, 1.0, 2.0]]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"k": 6}, "only 5"),
        ({"k": 0}, "positive"),
        ({"query_masks": torch.zeros(3)}, "query_masks"),
        ({"train_labels": torch.tensor([0, 1])}, "train_labels"),
        ({"train_labels": LABELS.float()}, "integer"),
        ({"label": torch.tensor([0, 1, 0])}, "one per query"),
        ({"label": 0.5}, "integer"),
        ({"train_masks": torch.zeros(5)}, "train_masks"),
    ],
)
def test_bad_arguments_raise(kwargs: dict, match: str) -> None:
    arguments = {"query_masks": torch.zeros(2, 2), "train_masks": STORED, "train_labels": LABELS, "k": 3, "label": 0}
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        confidence_score(**arguments)


def test_top_k_accuracy_on_a_constructed_example() -> None:
    # Link lengths on a line; property nearest neighbours: 0->1, 1->0, 2->3, 3->2, 4->3.
    lengths = torch.tensor([[0.0], [1.0], [10.0], [11.0], [13.0]])
    # Masks: item 0's mask-nearest are 2 then 1 (rank 1); 1's nearest is 0 (rank 0);
    # 2's are 0 then 3 (rank 1); 3's are 4 then 2 (rank 1); 4's nearest is 3 (rank 0).
    masks = torch.tensor([[0.0], [-1.5], [1.4], [4.0], [4.5]])
    accuracy = top_k_neighbour_accuracy(masks, lengths, ks=[1, 2, 4])
    assert accuracy.tolist() == pytest.approx([2 / 5, 1.0, 1.0])


def test_top_k_accuracy_of_unrelated_masks_is_chance() -> None:
    """Random masks: the property neighbour's mask rank is uniform, so accuracy at k is k / (n - 1).

    With n = 400 a hit rate at k = 40 has mean 0.1 and binomial std 0.015: 0.05 is over 3 sigma.
    """
    generator = torch.Generator().manual_seed(0)
    masks, lengths = torch.rand(400, 64, generator=generator), torch.rand(400, 2, generator=generator)
    accuracy = top_k_neighbour_accuracy(masks, lengths, ks=[40, 399])
    assert abs(float(accuracy[0]) - 40 / 399) < 0.05 and float(accuracy[1]) == 1.0


def test_top_k_accuracy_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="only 3"):
        top_k_neighbour_accuracy(torch.zeros(4, 2), torch.zeros(4, 1), ks=[4])
    with pytest.raises(ValueError, match="one row per item"):
        top_k_neighbour_accuracy(torch.zeros(4, 2), torch.zeros(3, 1), ks=[1])
    with pytest.raises(ValueError, match="at least 2"):
        top_k_neighbour_accuracy(torch.zeros(1, 2), torch.zeros(1, 1), ks=[1])
    with pytest.raises(ValueError, match="at least one k"):
        top_k_neighbour_accuracy(torch.zeros(4, 2), torch.zeros(4, 1), ks=[])
