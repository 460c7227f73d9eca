"""episodes: fixed-length windows cut from collected transitions never cross a reset."""

import gymnasium
import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.integrations.gymnasium import collect_transitions


def _stream(lengths: list[int], *, flag: str = "done", running: int = 0) -> TensorDict:
    """Episodes of the given lengths back to back, then ``running`` steps of an unfinished one.

    Each transition records which episode it belongs to and its step in it, so a window's
    contents show whether it crosses a reset.
    """
    episode = torch.cat([torch.full((n,), i) for i, n in enumerate([*lengths, running])])
    step = torch.cat([torch.arange(n) for n in [*lengths, running]])
    end = torch.zeros(len(step), dtype=torch.bool)
    end[torch.tensor(lengths, dtype=torch.long).cumsum(0) - 1] = True
    index = torch.arange(len(step))
    return TensorDict(
        {"episode": episode, "step": step, "index": index, "observation": torch.randn(len(step), 3)}
        | {"next": {flag: end.unsqueeze(-1)}},
        [len(step)],
    )


def _check_windows(windows: TensorDict, length: int) -> None:
    """Every window is one episode's steps k*length .. k*length + length - 1, in order."""
    assert windows.batch_size[1:] == (length,)
    episode, step = windows["episode"], windows["step"]
    assert (episode == episode[:, :1]).all(), "a window crosses a reset"
    assert (step == step[:, :1] + torch.arange(length)).all(), "a window's steps are not consecutive"
    assert (step[:, 0] % length == 0).all(), "windows do not tile each episode from its start"


@pytest.mark.parametrize("flag", ["done", "terminated", "truncated"])
@pytest.mark.parametrize("length", [1, 2, 3, 5])
def test_windows_stay_inside_one_episode_and_are_as_many_as_the_boundaries_allow(flag: str, length: int) -> None:
    lengths, running = [3, 7, 1, 5, 10, 4], 6
    data = _stream(lengths, flag=flag, running=running)
    windows = smcd_rl.episodes(data, length)
    _check_windows(windows, length)
    assert windows.batch_size[0] == sum(n // length for n in [*lengths, running])
    # Each episode gives its windows in order: the (episode, first step) pairs are exactly these.
    expected = [(i, k * length) for i, n in enumerate([*lengths, running]) for k in range(n // length)]
    assert list(zip(windows["episode"][:, 0].tolist(), windows["step"][:, 0].tolist(), strict=True)) == expected
    assert torch.equal(windows["observation"], data["observation"][windows["index"]])  # every key cut alike


def test_the_flags_are_joined_and_rows_of_a_batch_are_separate_streams() -> None:
    """terminated on one step, truncated on another; two envs' streams of 12 steps, [E, T]."""
    rows = []
    for ends in ([3, 7], [5]):
        td = _stream([], running=12)
        td["episode"] = torch.zeros(12, dtype=torch.long)
        terminated, truncated = torch.zeros(12, 1, dtype=torch.bool), torch.zeros(12, 1, dtype=torch.bool)
        terminated[ends[0]] = True
        truncated[ends[-1]] = True
        for t in range(12):
            td["episode"][t] = sum(t > e for e in ends)
            td["step"][t] = t - max([e + 1 for e in ends if t > e], default=0)
        del td["next", "done"]
        td["next", "terminated"], td["next", "truncated"] = terminated, truncated
        rows.append(td)
    stacked = torch.stack(rows)
    stacked["episode"] = stacked["episode"] + torch.tensor([[0], [10]])  # row 1's episodes are others
    windows = smcd_rl.episodes(stacked, 2)
    _check_windows(windows, 2)
    # Row 0: episodes of 4, 4, 4 steps give 2 + 2 + 2; row 1: 6 and 6 give 3 + 3. No window spans rows.
    assert windows.batch_size == (12, 2)
    assert windows["episode"][:, 0].tolist() == [0, 0, 1, 1, 2, 2, 10, 10, 10, 11, 11, 11]


def test_padding_of_torchrl_split_trajectories_belongs_to_no_episode() -> None:
    td = _stream([2, 3], running=0)
    padded = torch.cat([td, td[:1]], 0)  # as split_trajs pads: a step that is not a transition
    padded["collector", "mask"] = torch.tensor([True] * 5 + [False])
    padded["step"][-1] = 99
    windows = smcd_rl.episodes(padded, 1)
    assert windows.batch_size == (5, 1) and 99 not in windows["step"]


def test_transitions_from_collect_transitions_are_cut_at_its_resets() -> None:
    env = gymnasium.make("Pendulum-v1", max_episode_steps=7)
    data = collect_transitions(env, None, 30, seed=0)  # 4 episodes of 7, then 2 steps of a fifth
    windows = smcd_rl.episodes(data, 3)
    assert windows.batch_size == (8, 3)
    # Inside a window each observation is the previous step's next observation: no reset in between.
    assert torch.equal(windows["observation"][:, 1:], windows["next", "observation"][:, :-1])
    assert not windows["next", "done"][:, :-1].any()


@pytest.mark.parametrize(
    ("make", "length", "error", "message"),
    [
        (lambda: _stream([3, 2]), 4, ValueError, r"no episode has 4 consecutive transitions \(the longest has 3"),
        (lambda: _stream([3, 2]), 0, ValueError, "length must be >= 1"),
        (lambda: _stream([3, 2]), 2.0, TypeError, "length must be an int"),
        (lambda: TensorDict({"observation": torch.zeros(5, 3)}, [5]), 2, KeyError, r"\('next', 'done'\)"),
        (lambda: torch.stack([torch.stack([_stream([2, 2])] * 2)] * 2), 2, ValueError, r"got batch \[2, 2, 4\]"),
        (
            lambda: TensorDict({"next": {"done": torch.zeros(1, dtype=torch.bool)}}, []),
            1,
            ValueError,
            r"got batch \[\]",
        ),
        (
            lambda: TensorDict({"next": {"done": torch.zeros(4, 2, dtype=torch.bool)}}, [4]),
            1,
            ValueError,
            "one flag per",
        ),
        (lambda: TensorDict({"next": {"done": torch.zeros(4, 1)}}, [4]), 1, TypeError, "must be a bool tensor"),
        (lambda: {"next": {"done": torch.zeros(4, 1, dtype=torch.bool)}}, 1, TypeError, "takes a tensordict"),
        # Once "pass length <= 0", which no length is: the stream is empty.
        (lambda: _stream([], running=0), 1, ValueError, "got no transitions.*collect transitions first"),
    ],
    ids=[
        "too long",
        "zero",
        "float",
        "no flags",
        "3-d batch",
        "0-d batch",
        "flag shape",
        "flag dtype",
        "dict",
        "empty",
    ],
)
def test_bad_input_is_refused_with_the_problem_and_the_fix(make, length, error, message) -> None:
    with pytest.raises(error, match=message):
        smcd_rl.episodes(make(), length)
