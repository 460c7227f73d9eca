"""The T family: methods on a network whose dropout masks were trained to identify the task.

``T`` is the experiments' name for a network trained by :func:`smcd_rl.fit` with
``mask_training="task"``; ``T+S`` adapts it with SMCD tuned by one-step error. Its report table
pairs T+S with what it is meant to beat (:data:`TASK_AGAINST`) over the same trials.

Example:
    >>> c = {"k": 1, "method": "T+S", "against": "M+G", "difference": -0.1, "low": -0.2, "high": -0.05,
    ...      "verdict": "better"}
    >>> list(task_verdict_table([c], cell=["k"], over="episodes"))
    ["T+S (masks trained to identify the task) paired with M+G over the same episodes (negative: T+S's error is lower)"]
    >>> reversed = {**c, "method": "M+G", "against": "T+S", "difference": 0.1, "low": 0.05, "high": 0.2,
    ...             "verdict": "worse"}
    >>> print(task_verdict_table([reversed], cell=["k"], over="episodes").popitem()[1])
    | k | method | against | difference [95% CI]     | verdict |
    |---|--------|---------|-------------------------|---------|
    | 1 | T+S    | M+G     | -0.100 [-0.200, -0.050] | better  |
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from smcd_rl.experiments.shared.stats import verdict_table

__all__ = ["TASK_AGAINST", "task_verdict_table", "task_mask_settings"]

#: What T+S is paired with in its table: SMCD and GD on the multi-task network, GD on Reptile's,
#: and the task-mask network's own GD and no adaptation.
TASK_AGAINST = ("M+S", "M+G", "R+G", "T+G", "T+N")


def task_mask_settings(config: Any) -> dict[str, Any]:
    """What :func:`smcd_rl.fit` adds to M's settings to train T: masks tied to the data's ``"task"``.

    Example:
        >>> from types import SimpleNamespace
        >>> task_mask_settings(SimpleNamespace(task_share=1.0))
        {'mask_training': 'task', 'task_share': 1.0, 'group_masks': False}
    """
    # The network's grouping is the command's --mask-groups (0: one bit per unit), not fit's default.
    return {"mask_training": "task", "task_share": config.task_share, "group_masks": False}


def task_verdict_table(
    comparisons: Sequence[Mapping[str, Any]],
    *,
    cell: Sequence[str],
    over: str,
    against: Sequence[str] = TASK_AGAINST,
    lower_is_better: bool = True,
) -> dict[str, str]:
    """Caption -> Markdown of T+S's paired verdicts against ``against``; empty where T+S did not run.

    ``against`` names the methods as the experiment labels them (:data:`TASK_AGAINST` by default).
    A pair stored the other way round (the other method minus T+S, as when T+S stood in for a
    baseline that did not run) is turned round, so every row reads T+S minus the other.
    """
    verdicts = [c for c in comparisons if c["method"] == "T+S" and c["against"] in against]
    verdicts += [_turned(c) for c in comparisons if c["against"] == "T+S" and c["method"] in against]
    if not verdicts:
        return {}
    names = ", ".join(sorted({c["against"] for c in verdicts}))
    sign = "negative: T+S's error is lower" if lower_is_better else "positive: T+S scores higher"
    caption = f"T+S (masks trained to identify the task) paired with {names} over the same {over} ({sign})"
    return {caption: verdict_table(verdicts, cell=cell)}


def _turned(c: Mapping[str, Any]) -> dict[str, Any]:
    """Comparison ``c`` (other minus T+S) as T+S minus the other."""
    verdict = {"better": "worse", "worse": "better"}.get(c["verdict"], c["verdict"])
    turned = {"method": "T+S", "against": c["method"], "verdict": verdict}
    return {**c, **turned, "difference": -c["difference"], "low": -c["high"], "high": -c["low"]}
