"""Jobs beyond one process (`vfdata.executor`): the local executor, Ray imported only when asked, and
(slow, on a local Ray instance of 2 CPUs) `vfdata process --many` and `vfdata experiment` on Ray giving
what the local executor gives, and our recordings read by `ray.data.read_mcap`."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vfdata.cli import main
from vfdata.errors import VisionForceError
from vfdata.executor import run_jobs


def _square(x: int) -> int:
    return x * x


def test_the_local_executor_keeps_the_jobs_order():
    assert list(run_jobs(_square, [3, 1, 2])) == [9, 1, 4]
    assert list(run_jobs(_square, [3, 1, 2, 5], workers=2)) == [9, 1, 4, 25]
    with pytest.raises(VisionForceError, match="unknown executor 'dask'"):
        list(run_jobs(_square, [1], "dask"))


def test_ray_is_imported_only_when_asked():
    code = ("import sys\n"
            "from vfdata.executor import run_jobs\n"
            "import vfdata.commands.process, vfmodels.experiment.runner, vfmodels.commands.experiment\n"
            "assert list(run_jobs(abs, [-1, 2])) == [1, 2]\n"
            "print(sorted(m for m in sys.modules if m == 'ray' or m.startswith('ray.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_ray_missing_is_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(VisionForceError, match=r"pip install 'visionforce\[ray\]'"):
        list(run_jobs(_square, [1], "ray"))


def test_process_many_arguments(tmp_path, capsys):
    a, b, c = (tmp_path / f"{k}.mcap" for k in "abc")
    assert main(["process", str(a), str(b), str(c)]) == 1
    assert "--many" in capsys.readouterr().err
    assert main(["process", str(a), "--executor", "ray"]) == 1
    assert "are for --many" in capsys.readouterr().err
    assert main(["process", "--many", str(a), str(b)]) == 1
    assert f"{a}: recording not found" in capsys.readouterr().err


# ---- on a local Ray instance ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
    from vfdata.sim import synthesize

    root = tmp_path_factory.mktemp("sim")
    synthesize("mini", root, seed=3, frames=6, workers=1, progress=False)
    return [convert_raw_folder(root / f"mini_00{k}", root / f"mini_00{k}.mcap", options=ConvertOptions(progress=False))
            for k in range(3)]


def _contents(path: Path) -> tuple[list, dict]:
    """Every message (topic, log time, payload bytes) in file order, and the metadata records."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        reader = make_reader(stream)
        messages = [(c.topic, m.log_time, bytes(m.data)) for _, c, m in reader.iter_messages(log_time_order=False)]
        metadata = {r.name: dict(r.metadata) for r in reader.iter_metadata()}
    return messages, metadata


@pytest.mark.slow
def test_process_many_on_ray_writes_what_the_local_executor_writes(ray_instance, recordings, tmp_path, capsys):
    from vfdata.processing import default_output, preview_path

    assert main(["process", "--many", *map(str, recordings), "--quiet"]) == 0
    local = tmp_path / "local"
    local.mkdir()
    for src in recordings:
        for path in (default_output(src), preview_path(default_output(src))):
            shutil.move(path, local / path.name)
    assert main(["process", "--many", *map(str, recordings), "--executor", "ray", "--quiet"]) == 0
    for src in recordings:
        out = default_output(src)
        messages, metadata = _contents(out)
        local_messages, local_metadata = _contents(local / out.name)
        assert messages == local_messages and len(messages) > 0  # every payload, byte for byte
        # the metadata too, but for what was measured (stage rates, the machine's load: any two runs differ)
        timed, measured = "visionforce.derived", ("stage_fps", "stage_load_1min")
        assert {k: v for k, v in metadata[timed].items() if k not in measured} == \
            {k: v for k, v in local_metadata[timed].items() if k not in measured}
        assert preview_path(out).read_bytes() == (local / preview_path(out).name).read_bytes()
    capsys.readouterr()
    # Resumable: a second run keeps what exists.
    assert main(["process", "--many", *map(str, recordings), "--executor", "ray"]) == 0
    assert "3 of 3 recordings already processed: kept" in capsys.readouterr().out


@pytest.mark.slow
def test_ray_data_reads_our_recordings(ray_instance, recordings):
    """`ray.data.read_mcap` on our files: topics, counts, a time range; payloads stay CDR bytes."""
    import ray.data

    from vfdata.recording import Recording, layout

    src = recordings[0]
    with Recording.open(src) as rec:
        counts = {topic: info.count for topic, info in rec.topics.items()}
        force_times = rec.log_times_ns(layout.WRENCH)
        first_payload = next(iter(rec.payloads(layout.WRENCH)))
    rows = ray.data.read_mcap(str(src), topics={layout.WRENCH, layout.ECM_POSE}).take_all()
    by_topic = {t: sum(r["topic"] == t for r in rows) for t in (layout.WRENCH, layout.ECM_POSE)}
    assert by_topic == {layout.WRENCH: counts[layout.WRENCH], layout.ECM_POSE: counts[layout.ECM_POSE]}
    force = sorted((r for r in rows if r["topic"] == layout.WRENCH), key=lambda r: r["log_time"])
    assert force[0]["schema_name"] == "geometry_msgs/msg/WrenchStamped" and force[0]["message_encoding"] == "cdr"
    assert bytes(force[0]["data"]) == bytes(first_payload[1])  # CDR, undecoded
    start, end = int(force_times[10]), int(force_times[40])
    window = ray.data.read_mcap(str(src), topics={layout.WRENCH}, time_range=(start, end)).count()
    assert window == int(((force_times >= start) & (force_times < end)).sum())


@pytest.mark.slow
def test_an_experiment_on_ray_gives_the_local_metrics(ray_instance, tmp_path):
    """Preparation (convert + process) and training runs as Ray tasks: the same metrics as locally."""
    from vfdata.sim import synthesize
    from vfmodels.experiment import runner

    results = {}
    for executor in ("local", "ray"):
        manifest = synthesize("mini", tmp_path / executor / "data", seed=0, workers=1, progress=False, frames=24)
        options = runner.ExperimentOptions(seeds=2, epochs=1, variants=["visionforce"], progress=False,
                                           executor=executor)
        runner.run_experiment(manifest, tmp_path / executor / "results", options)
        results[executor] = [json.loads((tmp_path / executor / "results" / "runs" / "visionforce" / f"seed{s}" /
                                         "metrics.json").read_text()) for s in range(2)]
    timing = {"checkpoint", "config", "setup_seconds", "train_seconds", "force_fps", "torch_threads"}
    for local, remote in zip(results["local"], results["ray"], strict=True):
        assert {k: v for k, v in local.items() if k not in timing} == \
            {k: v for k, v in remote.items() if k not in timing}


@pytest.mark.slow
def test_a_failing_ray_task_is_the_jobs_own_one_line_error(ray_instance, tmp_path):
    from vfdata.commands.process import process_job
    from vfdata.errors import InputError
    from vfdata.processing import ProcessOptions

    bad = tmp_path / "bad.mcap"
    bad.write_text("not an MCAP")
    with pytest.raises(InputError) as caught:
        list(run_jobs(process_job, [(str(bad), str(tmp_path / "out.mcap"), ProcessOptions(progress=False), False)],
                      "ray"))
    assert str(caught.value).startswith(str(bad)) and "\n" not in str(caught.value)
    assert not list(tmp_path.glob("*out.mcap*"))


def test_our_errors_cross_process_boundaries_whole():
    """A job's error comes back from a worker process (or a Ray task) as it was raised."""
    import pickle

    from vfdata.errors import FormatError, InputError, OutputError, OutputExistsError

    for error in (InputError("a.mcap", "bad"), FormatError("b.mcap", "damaged"), OutputExistsError("c.mcap"),
                  OutputError("d.mcap", "disk full")):
        again = pickle.loads(pickle.dumps(error))
        assert type(again) is type(error) and str(again) == str(error) and again.path == error.path
    from vfdata.mcap_io.file import CorruptChunkError

    chunk = pickle.loads(pickle.dumps(CorruptChunkError("e.mcap", 1024, ["/tf"], "fails its CRC")))
    assert chunk.chunk_offset == 1024 and chunk.topics == ["/tf"] and "byte 1024" in str(chunk)
