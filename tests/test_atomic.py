"""Atomic outputs (vfdata/atomic.py): inputs never replaced, no output replaced without --overwrite
even by a race, nothing left behind on errors, signals or a full disk, stale temporaries cleaned."""

from __future__ import annotations

import errno
import multiprocessing
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rawfixtures import make_raw

from vfdata import atomic
from vfdata.atomic import atomic_output, atomic_outputs, remove_stale_temporaries
from vfdata.cli import main
from vfdata.errors import InputError, OutputError, OutputExistsError

ROOT = Path(__file__).resolve().parents[1]


def vfdata(*args: str, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "vfdata", *args], capture_output=True, text=True, env=env,
                          timeout=120, **kwargs)


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    return make_raw(tmp_path_factory.mktemp("raw") / "rec", n=6)


def test_output_that_is_an_input_is_refused(raw, tmp_path, capsys):
    before = (raw / "force.csv").read_bytes()
    link = tmp_path / "force_link.csv"
    os.link(raw / "force.csv", link)
    symlink = tmp_path / "force_symlink.csv"
    symlink.symlink_to(raw / "force.csv")
    for out in (raw / "force.csv", raw / "left" / "000001.png", raw, link, symlink, raw.parent):
        assert main(["convert", "--quiet", "--overwrite", str(raw), str(out)]) == 1, out
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "write the output elsewhere" in err, err
    assert (raw / "force.csv").read_bytes() == before and (raw / "left" / "000001.png").is_file()
    # `vfdata process X.mcap X.mcap`: the same check, for any caller of atomic_output
    recording = tmp_path / "x.mcap"
    recording.write_bytes(b"recording")
    os.link(recording, tmp_path / "y.mcap")
    for out in (recording, tmp_path / "y.mcap"):
        with pytest.raises(InputError, match="input"), atomic_output(out, overwrite=True, inputs=[recording]):
            pass
    assert recording.read_bytes() == b"recording"
    with atomic_output(tmp_path / "z.mcap", overwrite=True, inputs=[recording]) as tmp:  # a new file is fine
        tmp.write_bytes(b"derived")
    assert (tmp_path / "z.mcap").read_bytes() == b"derived"
    with atomic_output(tmp_path / "old.mcap") as tmp:  # the old signature still works
        tmp.write_bytes(b"x")


def test_special_files_are_never_replaced(raw, tmp_path, capsys):
    """`vfdata convert --overwrite RAW /dev/null` replaced /dev/null with a regular file (as root).
    Checked here on a FIFO and a character device node of our own, never on the real one."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    nodes = [fifo, tmp_path / "stdout_link"]
    nodes[1].symlink_to(fifo)
    if os.geteuid() == 0:
        nodes.append(tmp_path / "null")
        os.mknod(nodes[-1], 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    for node in nodes:
        assert main(["convert", "--quiet", "--overwrite", str(raw), str(node)]) == 1
        err = capsys.readouterr().err.strip()
        assert err.endswith("is not a regular file (a device, FIFO or socket): write the output to a file"), err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and nodes[1].is_symlink()
    assert os.geteuid() != 0 or stat.S_ISCHR(os.stat(nodes[-1]).st_mode)


def _publish_in_child(path: str) -> None:
    with atomic_output(path) as tmp:
        Path(tmp).write_bytes(b"child")


@pytest.mark.parametrize("renameat2", [True, False], ids=["renameat2", "link"])
def test_publishing_never_replaces_a_file_that_appeared_meanwhile(tmp_path, monkeypatch, renameat2):
    """Two runs writing one output without --overwrite: both pass the start check, the first to publish
    wins, the other gets OutputExistsError at its publish and leaves nothing behind."""
    if not renameat2:
        monkeypatch.setattr(atomic, "_RENAMEAT2", None)
    elif atomic._RENAMEAT2 is None:
        pytest.skip("no renameat2 here")
    out = tmp_path / "out.mcap"
    with pytest.raises(OutputExistsError), atomic_output(out) as tmp:
        tmp.write_bytes(b"parent")
        child = multiprocessing.get_context("fork").Process(target=_publish_in_child, args=(str(out),))
        child.start()
        child.join()
        assert child.exitcode == 0
    assert out.read_bytes() == b"child"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]
    with atomic_output(out, overwrite=True) as tmp:  # --overwrite still replaces
        tmp.write_bytes(b"new")
    assert out.read_bytes() == b"new"


def test_folder_outputs_publish_without_replacing(tmp_path):
    out = tmp_path / "folder"
    with atomic_output(out) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("a")
    with pytest.raises(OutputExistsError), atomic_output(tmp_path / "other") as tmp:
        tmp.mkdir()
        (tmp_path / "other").mkdir()  # appeared meanwhile
    assert (out / "a").read_text() == "a" and list((tmp_path / "other").iterdir()) == []


def test_two_concurrent_converts_to_one_output(raw, tmp_path):
    out = tmp_path / "out.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    runs = [subprocess.Popen([sys.executable, "-m", "vfdata", "convert", "--quiet", "--format", "png", str(raw),
                              str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            for _ in range(2)]
    results = [(run.wait(timeout=120), run.stderr.read()) for run in runs]
    assert sorted(code for code, _ in results) == [0, 1], results
    assert "output exists" in next(err for code, err in results if code == 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]


def test_stale_temporaries_of_gone_processes_are_removed(raw, tmp_path):
    out = tmp_path / "rec.mcap"
    stale, folder, live = (tmp_path / f".rec.mcap.tmp-{pid}" for pid in (dead_pid(), dead_pid() + 100000, 1))
    stale.write_bytes(b"x" * 1000)
    folder.mkdir()
    (folder / "part").write_bytes(b"y")
    live.write_bytes(b"pid 1 is alive: not ours to remove")
    other = tmp_path / ".other.mcap.tmp-99999999"
    other.write_bytes(b"another output's")
    assert main(["convert", "--quiet", str(raw), str(out)]) == 0
    assert not stale.exists() and not folder.exists() and live.exists() and other.exists()
    assert remove_stale_temporaries(tmp_path / "other.mcap") == [other]


def test_sigterm_cleans_up_like_ctrl_c(tmp_path):
    # Long enough that the signal, sent once the temporary appears, lands while frames are still being
    # written on a loaded machine (150 frames finished first once, under a parallel benchmark).
    src = make_raw(tmp_path / "rec", n=600, width=320, height=256)
    out = tmp_path / "out" / "rec.mcap"
    out.parent.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for signum, code in ((signal.SIGTERM, 143), (signal.SIGHUP, 129)):
        # A suite started under nohup hands SIGHUP down ignored, and the command rightly keeps it so.
        run = subprocess.Popen([sys.executable, "-m", "vfdata", "convert", "--quiet", "--format", "png", "--workers",
                                "1", str(src), str(out)], stderr=subprocess.PIPE, text=True, env=env,
                               preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
        deadline = time.monotonic() + 60
        while not any(out.parent.iterdir()) and time.monotonic() < deadline:
            time.sleep(0.01)
        run.send_signal(signum)
        assert run.wait(timeout=60) == code
        err = run.stderr.read().strip()
        assert err.splitlines() == [f"vfdata convert: terminated (signal {int(signum)})"], err
        assert list(out.parent.iterdir()) == []  # no output, no temporary


def test_full_disk_names_the_output_and_leaves_nothing(raw, tmp_path):
    """A real full disk: a 1 MB tmpfs mounted in a user namespace of our own."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    small = tmp_path / "small"
    small.mkdir()
    script = (f"mount -t tmpfs -o size=256k tmpfs {small} || exit 99; "
              f"{sys.executable} -m vfdata convert --quiet --format png {raw} {small}/rec.mcap; echo rc=$?; "
              f"ls -A {small}")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, env=env,
                          timeout=120)
    if "rc=" not in done.stdout:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    assert done.stdout.split() == ["rc=1"], done.stdout  # and the tmpfs is empty
    err = done.stderr.strip()
    assert err.splitlines() == [f"vfdata convert: error: {small}/rec.mcap: no space left on the device (or quota "
                                "exceeded); nothing was written: free some space or write the output elsewhere"]


def test_disk_full_inside_atomic_output_is_named(tmp_path):
    out = tmp_path / "x.bin"
    with pytest.raises(OutputError, match=r"x\.bin: no space left"), atomic_output(out) as tmp:
        with open("/dev/full", "wb") as full:
            tmp.write_bytes(b"partial")
            full.write(b"x" * 10)
            full.flush()
    assert list(tmp_path.iterdir()) == []


def test_outputs_that_belong_together_are_published_together(tmp_path):
    a, b = tmp_path / "a.mcap", tmp_path / "a.preview.png"
    with pytest.raises(RuntimeError), atomic_outputs([a, b]) as (ta, tb):
        ta.write_bytes(b"a")
        tb.write_bytes(b"b")
        raise RuntimeError("the preview failed")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OutputExistsError), atomic_outputs([a, b]) as (ta, tb):
        ta.write_bytes(b"a")
        tb.write_bytes(b"b")
        b.write_bytes(b"appeared meanwhile")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.preview.png"]  # a.mcap published, then removed
    b.unlink()
    with atomic_outputs([a, b]) as (ta, tb):
        ta.write_bytes(b"a")
        tb.write_bytes(b"b")
    assert a.read_bytes() == b"a" and b.read_bytes() == b"b"


def test_a_writer_given_a_members_temporary_names_the_output(tmp_path):
    """A writer that is atomic itself (McapWriter) writing into a temporary of `atomic_outputs`: a full
    disk names the output the user asked for, not either temporary; `overwrite` may differ per output."""
    a, b = tmp_path / "a.mcap", tmp_path / "a.png"
    b.write_bytes(b"older picture")
    with pytest.raises(OutputError, match=r"a\.mcap: no space left") as info, \
            atomic_outputs([b, a], overwrite=(True, False)) as (tb, ta), atomic_output(ta) as inner:
        tb.write_bytes(b"b")
        inner.write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device", str(inner))
    assert info.value.path == a
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"] and b.read_bytes() == b"older picture"
