"""The files an experiment writes: atomic even for plots, a full disk named in one line, damaged
caches named with the fix, one run at a time in an output directory."""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest
import torch

import smcd_rl.files
from smcd_rl import cli
from smcd_rl.experiments.shared.harness import Experiment, ExperimentConfig
from smcd_rl.experiments.shared.outputs import save_figure, write_csv
from smcd_rl.experiments.shared.result_store import ResultStore
from smcd_rl.files import FileWriteError, UnreadableFileError


def _full_disk(monkeypatch: pytest.MonkeyPatch, *, free: int, suffix: str, code: int = errno.ENOSPC) -> None:
    """Make the disk hold only ``free`` more bytes of each file whose name ends in ``suffix``, as a full disk does."""

    class FullDisk(smcd_rl.files._TempFile):
        def write(self, data):  # type: ignore[no-untyped-def]
            data = memoryview(data).cast("B")
            if f"{suffix}." not in Path(str(self.name)).name:  # another file: room enough
                return super().write(data)
            room = free - self.tell()
            if len(data) <= room:
                return super().write(data)
            if room > 0:
                super().write(data[:room])
            raise OSError(code, os.strerror(code))

    monkeypatch.setattr(smcd_rl.files, "_TempFile", FullDisk)


def _figure():  # type: ignore[no-untyped-def]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot(range(100))
    return fig


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT])
def test_a_plot_on_a_full_disk_names_the_file_and_the_space_it_needs_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, code: int
) -> None:
    """It used to be a raw ``OSError: [Errno 28]`` from PIL, with a truncated PNG left behind."""
    path = tmp_path / "plot.png"
    fig = _figure()
    save_figure(fig, path, dpi=50)
    before = path.read_bytes()
    _full_disk(monkeypatch, free=100, suffix=".png", code=code)
    with pytest.raises(FileWriteError) as caught:
        save_figure(fig, path, dpi=60)
    message = str(caught.value)
    assert message.startswith(f"cannot write plot {path}: ") and "\n" not in message
    assert ("no space left on the disk of" if code == errno.ENOSPC else "disk quota exceeded for") in message
    needed = float(message.split("the file needs ")[1].split(" kB")[0]) * 1000
    assert needed >= len(before) * 0.5 and "free at least that much space" in message  # dpi 60 is larger than 50
    assert path.read_bytes() == before  # the old picture is intact
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"]  # no temporary file left


def test_tables_and_reports_go_through_the_atomic_writer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "rows.csv"
    write_csv(path, [{"a": 1}])
    _full_disk(monkeypatch, free=3, suffix=".csv")
    with pytest.raises(FileWriteError, match="no space left"):
        write_csv(path, [{"a": 2}] * 100)
    assert path.read_text() == "a\n1\n" and [p.name for p in tmp_path.iterdir()] == ["rows.csv"]


def _fake_run(path: Path) -> None:
    entry = {
        "task": "task a",
        "cell": {"T": 10},
        "metric": "rmse",
        "unit": "m",
        "lower_is_better": True,
        "estimates": {"none": {"method": "M+N", "mean": 0.3, "low": 0.2, "high": 0.4, "trials": 9}},
        "verdicts": {},
    }
    path.mkdir()
    (path / "results.json").write_text(json.dumps({"scoreboard": entry}))


def test_a_full_disk_during_a_command_is_one_error_line_naming_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The disk fills while PIL writes the scoreboard's PNG: once a raw ``OSError`` and a truncated PNG."""
    from PIL import Image

    real = Image.Image.save

    def full_disk(self, target, *args, **kwargs):  # type: ignore[no-untyped-def]
        if isinstance(target, io.BytesIO):  # memory is not full
            return real(self, target, *args, **kwargs)
        with contextlib.ExitStack() as stack:
            handle = target if hasattr(target, "write") else stack.enter_context(open(target, "wb"))
            handle.write(b"\x89PNG\r\n\x1a\n" + bytes(100))  # the first bytes fit on the disk
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Image.Image, "save", full_disk)
    _fake_run(tmp_path / "a")
    out = tmp_path / "board"
    assert cli.main(["scoreboard", str(tmp_path / "a"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"error: cannot write plot {out / 'scoreboard.png'}: no space left on the disk of {out}" in err
    assert "the file needs" in err
    assert not list(out.glob("*.png")) and not list(out.glob(".*.tmp"))  # no truncated picture


# ---------------------------------------------------------------------------- damaged caches
TINY = ["--tasks", "2", "--episodes", "2", "--steps", "2", "--hidden", "8", "--epochs", "1", "--trials", "2"]


def _flip_bit(path: Path, near: bytes) -> None:
    data = bytearray(path.read_bytes())
    data[data.index(near)] ^= 1
    path.write_bytes(data)


def test_a_flipped_bit_in_a_partial_result_names_the_file_and_the_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bit flip in ``partial/`` used to end the rerun with ``error: 'sq_errors'``."""
    out = tmp_path / "run"
    command = ["two-link", "--out", str(out), *TINY, "--methods", "M+N"]
    assert cli.main(command) == 0
    (result,) = (out / "partial").glob("method-*.pt")
    _flip_bit(result, b"sq_errors")  # the entry's name in the pickled dict: it loads, without that entry
    capsys.readouterr()
    assert cli.main(command) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert str(result) in err and "is corrupt" in err and "delete it and rerun" in err, err


def test_a_flipped_bit_in_a_stored_tensor_is_found(tmp_path: Path) -> None:
    """torch.load does not check the CRC-32s torch.save writes: the bit would load as a wrong number."""
    store = ResultStore(tmp_path, what="cached result")
    store.put("tuning", {"k": 1}, {"errors": torch.full((64,), 0.25)})
    path = store.path("tuning", {"k": 1})
    _flip_bit(path, torch.tensor(0.25).numpy().tobytes())
    with pytest.raises(UnreadableFileError, match="cached result file .* is corrupt.*delete it and rerun"):
        store.get("tuning", {"k": 1})


def test_a_flipped_bit_that_no_checksum_covers_is_found_too(tmp_path: Path) -> None:
    """Two bits outside every CRC-32 loaded as wrong numbers: a record's "directory" attribute in the
    archive's directory (torch.load then reads the tensor as uninitialised memory), and its name's
    length in its local header (the data read from the wrong offset; the header check raised a
    ValueError that was taken for "not a zip archive" and skipped). Found by flipping every bit of a
    small stored result: each of these two was the only flip that loaded silently."""
    store = ResultStore(tmp_path, what="cached result")
    store.put("tuning", {"k": 1}, {"loss": torch.tensor([0.5, 1.5, 2.5])})
    path = store.path("tuning", {"k": 1})
    raw = path.read_bytes()
    with zipfile.ZipFile(path) as archive:
        record = next(info for info in archive.infolist() if info.filename.endswith("/data/0"))
    directory_entry = raw.rfind(record.filename.encode()) - 46  # the central directory's header of the record
    for offset, mask in ((directory_entry + 38, 0x10), (record.header_offset + 26, 0x80)):
        damaged = bytearray(raw)
        damaged[offset] ^= mask
        path.write_bytes(damaged)
        with pytest.raises(UnreadableFileError, match="cached result file .* is corrupt.*delete it and rerun"):
            store.get("tuning", {"k": 1})


def test_a_result_that_is_not_a_mapping_is_refused(tmp_path: Path) -> None:
    store = ResultStore(tmp_path, what="cached result")
    store.put("point", {"k": 1}, {"x": 1})
    path = store.path("point", {"k": 1})
    entry = torch.load(path, weights_only=False)
    torch.save({**entry, "value": [1, 2]}, path)
    with pytest.raises(UnreadableFileError, match=f"{path} holds a list, not a result; delete it and rerun"):
        store.get("point", {"k": 1})


# ---------------------------------------------------------------------------- one run per --out
_HOLDER = textwrap.dedent(
    """
    import sys, time
    from smcd_rl.experiments.shared.harness import Experiment, ExperimentConfig
    with Experiment(ExperimentConfig(out=sys.argv[1]), progress=False):
        print("running", flush=True)
        time.sleep(120)
    """
)


def test_a_second_run_on_an_out_in_use_is_refused_and_a_crashed_run_leaves_no_lock(tmp_path: Path) -> None:
    """Two runs on one --out both used to exit 0, the first one's "wrote ..." naming the second's files."""
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "running"
        with pytest.raises(ValueError, match=rf"--out {out} is in use by another run \(process {holder.pid}: "):
            with Experiment(ExperimentConfig(out=str(out)), progress=False):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)  # a crash: no cleanup runs
        holder.wait()
        if holder.stdout is not None:
            holder.stdout.close()
    assert (out / ".lock").exists()  # left behind by the crash, and no obstacle: the OS released the lock
    with Experiment(ExperimentConfig(out=str(out)), progress=False):
        with pytest.raises(ValueError, match="is in use by another run"):  # also within one process
            with Experiment(ExperimentConfig(out=str(out)), progress=False):
                pass
    assert not (out / ".lock").exists()  # a run that ends removes its lock file
    with Experiment(ExperimentConfig(out=str(out)), progress=False):  # and the directory is free again
        pass
