"""Adversarial corpus, counted (issue 20). Runs the cases the tests hold, through the command line
where a user would meet them, and sorts every outcome into one of:

- clean: the original data, or one line naming the file and the problem with exit 1 (a truncated
  recording may also read as a part of the original with the damage listed in `problems`);
- silent corruption: data that differs from the original served without a problem listed (or a wrong
  value accepted at convert), and `vfdata check` does not find it either;
- modified input: a file the user gave changed;
- traceback: any other exception, an internal error, more than one line, a wrong exit status;
- code executed: a checkpoint ran a command.

    python bench/adversarial.py [--families mcap,convert,bags,checkpoints,outputs,edges] [--verbose]

Families: `mcap` (truncations every 5 % and 12 single-bit flips per region of a recording, read by
`Recording` as `damaged='error'` and `'skip'`, by `vfdata info` and `vfdata check`), `convert` (the raw
folder and bag corpus of tests/test_convert_corpus.py), `bags` (truncations every 5 % and bit flips of
ROS 1, ROS 1 lz4, ROS 2 sqlite and ROS 2 MCAP bags, through `vfdata convert`), `checkpoints` (damaged and malicious
checkpoints through `vfdata predict --ckpt` and `train.py test --ckpt_path`), `outputs` (outputs that
are inputs, SIGTERM, two converts to one output, stale temporaries; these run subprocesses), `edges` (the
rough edges of issue 34: FFmpeg's line before ours, a file named twice, inspect-bag's exit status, a full
disk at the preview, a checkpoint of another model than the config). Stderr is read at the file
descriptor, so what C libraries print themselves counts as a line.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from vfdata.cli import main as vfdata_main  # noqa: E402

OUTCOMES = ("clean", "silent corruption", "modified input", "traceback", "code executed")


def digest(path: Path) -> dict[str, str]:
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()) if path.exists() else []
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def cli(run, argv: list[str]) -> tuple[int, str]:
    """(exit status, stderr) of an in-process command line; SystemExit counts as its status. Stderr
    includes what C libraries write to file descriptor 2 themselves (FFmpeg's log, OpenCV's warnings)."""
    err = io.StringIO()
    with fd_stderr() as native, contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = run(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except Exception as exc:  # noqa: BLE001 - an escaping exception is what this counts
            return -1, f"Traceback: {type(exc).__name__}: {exc}"
    return int(code or 0), (native.read() + err.getvalue()).strip()


@contextlib.contextmanager
def fd_stderr():
    """File descriptor 2 into a temporary file for the block; yields a reader of what was written."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 2)
        written = io.StringIO()
        try:
            yield written
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            written.write(sink.read().decode(errors="replace"))
            written.seek(0)


def one_line_error(code: int, err: str, expect: str | None = None) -> bool:
    lines = [line for line in err.splitlines() if not line.startswith("warning:")]
    return (code == 1 and len(lines) == 1 and "internal error" not in err and "Traceback" not in err
            and (expect is None or expect in lines[0]))


# -- damaged recordings ------------------------------------------------------------------------------
def mcap_family(tmp: Path, verbose: bool) -> Counter:
    from test_mcap_damage import damaged_cases, outcome, read_all, write_pristine

    from vfdata.recording.inspect import check_file

    pristine = write_pristine(tmp / "pristine.mcap")
    reference = read_all(pristine)["view"]
    counts: Counter = Counter()
    path = tmp / "damaged.mcap"
    for name, data in damaged_cases(pristine.read_bytes()):
        path.write_bytes(data)
        before = digest(path)
        results = [outcome(path, reference), outcome(path, reference, damaged="skip")]
        commands = [cli(vfdata_main, [command, str(path)]) for command in ("info", "check")]
        check_problems = check_file(path)
        if digest(path) != before:
            verdict = "modified input"
        elif any(r.startswith("crash") for r in results) or any(
                "Traceback" in err or "internal error" in err or len(err.splitlines()) > 1 and code != 1
                for code, err in commands):
            verdict = "traceback"
        elif "altered" in results and not check_problems:
            verdict = "silent corruption"
        elif not check_problems and results[0] != "exact":
            verdict = "silent corruption"  # the reader saw damage that check does not: they must agree
        else:
            verdict = "clean"
        if "altered" in results and verdict == "clean":
            counts["  (altered in the reader, found by check: metadata text, which MCAP gives no CRC)"] += 1
        counts[verdict] += 1
        if verbose and verdict != "clean":
            print(f"  mcap {name}: {verdict} {results} {commands}")
    return counts


# -- convert corpus ----------------------------------------------------------------------------------
def convert_family(tmp: Path, verbose: bool) -> Counter:
    from test_convert_corpus import BAG_CASES, RAW_CASES

    from vfdata.recording import Recording

    counts: Counter = Counter()
    for i, case in enumerate(RAW_CASES + BAG_CASES):
        work = tmp / f"convert{i}"
        work.mkdir()
        src, args, out = case.build(work)
        if out is None:
            out = work / "out" / "rec.mcap"
            out.parent.mkdir(exist_ok=True)
        before = digest(src)
        code, err = cli(vfdata_main, ["convert", "--quiet", "--format", "png", *args, str(src), str(out)])
        if digest(src) != before:
            verdict = "modified input"
        elif "Traceback" in err or "internal error" in err or code not in (0, 1):
            verdict = "traceback"
        elif case.expect is None:
            verdict = "clean"
            try:
                rec = Recording.open(out)
                if code != 0 or rec.problems:
                    verdict = "traceback" if code != 1 else "silent corruption"
                elif case.check is not None:
                    case.check(rec, src)
            except BaseException:  # noqa: BLE001 - a value check failing is a wrong value accepted
                verdict = "silent corruption"
        elif code == 0:
            verdict = "silent corruption"  # a wrong value accepted
        else:
            verdict = "clean" if one_line_error(code, err, case.expect) else "traceback"
        counts[verdict] += 1
        if verbose and verdict != "clean":
            print(f"  convert {case.name}: {verdict}: {err[:300]}")
    return counts


# -- damaged bags -----------------------------------------------------------------------------------
def bags_family(tmp: Path, verbose: bool) -> Counter:
    """Truncations every 5 % and 15 single-bit flips of each storage; a conversion must give the
    original's values or one line. ROS 1, sqlite and rosbags' MCAP have no checksums over the
    messages: a flip inside a value there cannot be noticed by anyone (counted apart)."""
    import random

    import numpy as np
    from bagfixtures import BagSpec, write_bag
    from rosbags.rosbag2 import StoragePlugin
    from test_bag_index import _rewrite_mcap_bag

    from vfdata.recording import Recording

    def view(path: Path):
        rec = Recording.open(path)
        return rec.num_frames, rec.force.times_ns.tolist(), np.round(rec.force.wrench, 9).tolist()

    counts: Counter = Counter()
    storages = {"ROS 1": (BagSpec(frames=8), False), "ROS 1 lz4": (BagSpec(frames=8, lz4=True), False),
                "ROS 2 sqlite": (BagSpec(ros2=True, frames=8), False),
                "ROS 2 MCAP (rosbags, no CRC)": (BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=8), False),
                "ROS 2 MCAP (CRCs)": (BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=8), True)}
    for i, (label, (spec, crcs)) in enumerate(storages.items()):
        src = tmp / f"bag{i}" / ("bag" if spec.ros2 else "x.bag")
        src.parent.mkdir()
        write_bag(src, spec)
        data_file = src if src.is_file() else next(p for p in src.iterdir() if p.suffix in (".mcap", ".db3"))
        if crcs:
            _rewrite_mcap_bag(data_file)
        ref = src.parent / "ref.mcap"
        assert cli(vfdata_main, ["convert", "--quiet", "--format", "png", str(src), str(ref)])[0] == 0
        reference = view(ref)
        pristine = data_file.read_bytes()
        rng = random.Random(i)
        cases = [(f"truncated to {p}%", pristine[:len(pristine) * p // 100]) for p in range(5, 100, 5)]
        for _ in range(15):
            flipped = bytearray(pristine)
            at = rng.randrange(len(flipped))
            flipped[at] ^= 1 << rng.randrange(8)
            cases.append((f"bit flip at {at}", bytes(flipped)))
        for name, data in cases:
            data_file.write_bytes(data)
            before = digest(src)
            out = src.parent / "out.mcap"
            code, err = cli(vfdata_main, ["convert", "--quiet", "--format", "png", "--overwrite", str(src), str(out)])
            if digest(src) != before:
                verdict = "modified input"
            elif code == 0:
                verdict = "clean" if view(out) == reference else "silent corruption"
                if verdict != "clean" and not crcs:
                    counts[f"  (silent, in a {label} bag: the format has no checksum to notice it)"] += 1
            else:
                verdict = "clean" if one_line_error(code, err, str(src)) else "traceback"
            counts[verdict] += 1
            if verbose and verdict != "clean":
                print(f"  bag {label} {name}: {verdict}: {err[:300]}")
        data_file.write_bytes(pristine)
    return counts


# -- checkpoints -------------------------------------------------------------------------------------
def checkpoint_family(tmp: Path, verbose: bool) -> Counter:
    import test_train_cli
    from rawfixtures import make_raw

    import train

    rec = tmp / "rec.mcap"
    raw = make_raw(tmp / "raw", n=4)
    assert cli(vfdata_main, ["convert", "--quiet", "--format", "png", str(raw), str(rec)])[0] == 0
    bad = test_train_cli._bad_checkpoints(tmp)
    counts: Counter = Counter()
    argv0 = sys.argv
    sys.argv = ["train.py"]  # as from a shell (Lightning compares its args with sys.argv)
    try:
        for name, problem in bad.items():
            ckpt = tmp / name
            before = digest(ckpt) | digest(rec)
            runs = [("predict", cli(vfdata_main, ["predict", str(rec), "--ckpt", str(ckpt), "--out",
                                                  str(tmp / "pred"), "--quiet"])),
                    ("train.py test", cli(train.main, ["test", *test_train_cli.SYNTHETIC,
                                                       f"--trainer.default_root_dir={tmp / 'run'}",
                                                       f"--ckpt_path={ckpt}"]))]
            for how, (code, err) in runs:
                if (tmp / "ran").exists():
                    verdict = "code executed"
                    (tmp / "ran").unlink()
                elif digest(ckpt) | digest(rec) != before:
                    verdict = "modified input"
                elif code == 0:
                    verdict = "silent corruption"
                else:
                    verdict = "clean" if one_line_error(code, err, str(ckpt)) else "traceback"
                counts[verdict] += 1
                if verbose and verdict != "clean":
                    print(f"  checkpoint {name} via {how}: {verdict}: {err[:300]} (expected {problem})")
    finally:
        sys.argv = argv0
    return counts


# -- outputs: inputs as outputs, signals, races, stale temporaries ----------------------------------
def _vfdata(*args: str, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "vfdata", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **kwargs)


def outputs_family(tmp: Path, verbose: bool) -> Counter:
    from rawfixtures import make_raw

    counts: Counter = Counter()

    def record(name: str, verdict: str, detail: str = "") -> None:
        counts[verdict] += 1
        if verbose and verdict != "clean":
            print(f"  outputs {name}: {verdict}: {detail[:300]}")

    small = make_raw(tmp / "small", n=6)
    rec = tmp / "small.mcap"
    assert cli(vfdata_main, ["convert", "--quiet", "--format", "png", str(small), str(rec)])[0] == 0
    # the recording as the output of process, the force log as the output of convert, with --overwrite
    for name, argv, src in (("process X X", ["process", "--overwrite", "--quiet", str(rec), str(rec)], rec),
                            ("process X X-hardlink", ["process", "--overwrite", "--quiet", str(rec),
                                                      str(tmp / "link.mcap")], rec),
                            ("convert RAW RAW/force.csv", ["convert", "--overwrite", "--quiet", str(small),
                                                           str(small / "force.csv")], small)):
        if "hardlink" in name and not (tmp / "link.mcap").exists():
            os.link(rec, tmp / "link.mcap")
        before = digest(src)
        code, err = cli(vfdata_main, argv)
        verdict = ("modified input" if digest(src) != before else "clean" if one_line_error(code, err)
                   else "traceback")
        record(name, verdict, err)
    # SIGTERM in the middle of a conversion: exit 143, one line, nothing left
    big = make_raw(tmp / "big", n=120, width=320, height=256)
    out_dir = tmp / "sigterm"
    out_dir.mkdir()
    run = _vfdata("convert", "--quiet", "--format", "png", "--workers", "1", str(big), str(out_dir / "rec.mcap"))
    deadline = time.monotonic() + 60
    while not any(out_dir.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.01)
    run.send_signal(signal.SIGTERM)
    code = run.wait(timeout=60)
    err = run.stderr.read().strip()
    left = sorted(p.name for p in out_dir.iterdir())
    record("SIGTERM convert", "clean" if code == 143 and len(err.splitlines()) == 1 and not left else "traceback",
           f"{code} {err} {left}")
    # two converts to one output at once: one succeeds, the other says the output exists
    out = tmp / "race" / "rec.mcap"
    out.parent.mkdir()
    runs = [_vfdata("convert", "--quiet", "--format", "png", str(small), str(out)) for _ in range(2)]
    results = sorted((r.wait(timeout=120), r.stderr.read().strip()) for r in runs)
    ok = [c for c, _ in results] == [0, 1] and "output exists" in results[1][1]
    record("two converts", "clean" if ok and sorted(p.name for p in out.parent.iterdir()) == ["rec.mcap"]
           else "silent corruption", str(results))
    # a temporary of a process that is gone is removed by the next run
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = tmp / "stale" / f".rec.mcap.tmp-{gone.pid}"
    stale.parent.mkdir()
    stale.write_bytes(b"x" * 1000)
    code, err = cli(vfdata_main, ["convert", "--quiet", str(small), str(stale.parent / "rec.mcap")])
    record("stale temporary", "clean" if code == 0 and not stale.exists() else "traceback", err)
    return counts


# -- the rough edges of issue 34 -----------------------------------------------------------------
def edges_family(tmp: Path, verbose: bool) -> Counter:
    """Cases an earlier corpus let through as clean: FFmpeg's own line before ours, a file named twice,
    an exit 0 on a bag that cannot be converted, a derived MCAP left without its preview by a full
    disk, a checkpoint of another model than the config that names neither. Each is clean only as one
    line naming the file (exit 1) with nothing left behind."""
    import errno
    import shutil

    import cv2
    import numpy as np
    import test_train_cli
    from bagfixtures import BagSpec, write_bag
    from rawfixtures import make_raw

    import train

    counts: Counter = Counter()

    def record(name: str, clean: bool, detail: str) -> None:
        counts["clean" if clean else "traceback"] += 1
        if verbose and not clean:
            print(f"  edges {name}: not clean: {detail[:300]}")

    # convert on a video that does not open, in a fresh process (FFmpeg's log level is set once)
    for name in ("broken", "text"):
        src = make_raw(tmp / f"video_{name}", n=12)
        shutil.rmtree(src / "left")
        shutil.rmtree(src / "right")
        if name == "text":
            (src / "stereo.mp4").write_text("a note, not a video\n")
        else:
            writer = cv2.VideoWriter(str(src / "stereo.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (320, 128))
            for frame in np.random.default_rng(0).integers(0, 256, (12, 128, 320, 3), np.uint8):
                writer.write(frame)
            writer.release()
            data = (src / "stereo.mp4").read_bytes()
            (src / "stereo.mp4").write_bytes(data[:len(data) // 2])
        run = _vfdata("convert", "--quiet", str(src), str(tmp / f"video_{name}.mcap"))
        code, err = run.wait(timeout=120), run.stderr.read().strip()
        record(f"convert {name} MP4", one_line_error(code, err, str(src / "stereo.mp4"))
               and not (tmp / f"video_{name}.mcap").exists(), err)
    # check on a file that is not an MCAP
    path = tmp / "not.mcap"
    path.write_bytes(b"hello, not an mcap")
    code, err = cli(vfdata_main, ["check", str(path)])
    record("check not an MCAP", one_line_error(code, err) and err.count(str(path)) == 1, err)
    # inspect-bag on a bag without images
    bag = tmp / "noimages.bag"
    write_bag(bag, BagSpec(with_images=False, frames=2))
    code, err = cli(vfdata_main, ["inspect-bag", "--quiet", str(bag)])
    record("inspect-bag unconvertible", one_line_error(code, err, str(bag)), f"exit {code}: {err}")
    # a full disk while the preview PNG is written
    from vfdata.sim import synthesize

    synthesize("mini", tmp / "sim", frames=3, progress=False)  # a tissue the mask finds
    rec = tmp / "small.mcap"
    assert cli(vfdata_main, ["convert", "--quiet", "--format", "png", str(tmp / "sim" / "mini_002"), str(rec)])[0] == 0
    out = tmp / "full" / "small.processed.mcap"
    out.parent.mkdir()
    write_bytes = Path.write_bytes

    def full(self, data):
        if ".png" in self.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return write_bytes(self, data)

    Path.write_bytes = full
    try:
        code, err = cli(vfdata_main, ["process", "--quiet", "--tracker", "none", str(rec), str(out)])
    finally:
        Path.write_bytes = write_bytes
    left = sorted(p.name for p in out.parent.iterdir())
    record("process full disk at the preview", one_line_error(code, err) and not left, f"{err} left {left}")
    # train.py test with a checkpoint of another model than its config
    argv0 = sys.argv
    sys.argv = ["train.py"]
    try:
        cli(train.main, ["fit", *test_train_cli.SYNTHETIC, "--model.model.dim=16", "--trainer.max_epochs=1",
                         f"--trainer.default_root_dir={tmp / 'small_run'}"])
        ckpt = tmp / "small_run" / "checkpoints" / "last.ckpt"
        code, err = cli(train.main, ["test", *test_train_cli.SYNTHETIC, f"--trainer.default_root_dir={tmp / 'run'}",
                                     f"--ckpt_path={ckpt}"])
    finally:
        sys.argv = argv0
    record("train.py test, another model", one_line_error(code, err, str(ckpt)), err)
    return counts


FAMILIES = {"mcap": mcap_family, "convert": convert_family, "bags": bags_family, "checkpoints": checkpoint_family,
            "outputs": outputs_family, "edges": edges_family}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--verbose", action="store_true", help="print every case that is not clean")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    total: Counter = Counter()
    print(f"{'family':12} {'cases':>6} " + " ".join(f"{o:>17}" for o in OUTCOMES) + "   seconds")
    for name in args.families.split(","):
        with tempfile.TemporaryDirectory(prefix=f"vf_adv_{name}_") as tmp:
            start = time.perf_counter()
            counts = FAMILIES[name](Path(tmp), args.verbose)
            seconds = time.perf_counter() - start
        cases = sum(counts[o] for o in OUTCOMES)
        print(f"{name:12} {cases:6d} " + " ".join(f"{counts[o]:17d}" for o in OUTCOMES) + f"   {seconds:7.1f}")
        for note in sorted(k for k in counts if k not in OUTCOMES):
            print(f"{note}: {counts[note]}")
        total.update({o: counts[o] for o in OUTCOMES})
    print(f"{'total':12} {sum(total.values()):6d} " + " ".join(f"{total[o]:17d}" for o in OUTCOMES))


if __name__ == "__main__":
    main()
