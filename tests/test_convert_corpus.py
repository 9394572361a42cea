"""Adversarial corpus of `vfdata convert`: raw folders and bags with the defects users' files have
(and some an attacker would make), bad options, outputs that are inputs, unreadable files. Signals,
races and a full disk are in test_atomic.py.

Every case runs the CLI and must end cleanly: either exit 0 and a recording holding the values
given, or exit 1 and one line naming the file and the problem; never a traceback or an internal
error, no output or temporary file left behind on failure, the inputs unchanged byte for byte."""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from bagfixtures import T0_NS as BAG_T0_NS
from bagfixtures import BagSpec, write_bag
from rawfixtures import calibration, make_raw
from rosbags.rosbag2 import StoragePlugin

from vfdata.cli import main
from vfdata.recording import Recording

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Case:
    """`build(tmp)` makes the input and returns (src, extra CLI arguments, output path or None for
    tmp/out/rec.mcap); `expect` is a piece of the one-line error, or None when the input must convert
    (then `check(recording, src)` looks at the values)."""

    name: str
    build: Callable[[Path], tuple[Path, list[str], Path | None]]
    expect: str | None
    check: Callable[[Recording, Path], None] | None = None


def tree_digest(path: Path) -> dict[str, str]:
    if path.is_file():
        return {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


# -- raw folders -------------------------------------------------------------------------------------
def raw_case(name: str, edit: Callable[[Path], None], expect: str | None, check=None, args=(), out=None) -> Case:
    def build(tmp: Path):
        src = make_raw(tmp / "rec", n=6)
        edit(src)
        return src, list(args), out(src) if out else None
    return Case(name, build, expect, check)


def replace_line(file: str, line: int, text: str) -> Callable[[Path], None]:
    """Line `line` (1-based) of `file` becomes `text`."""
    def edit(src: Path) -> None:
        lines = (src / file).read_text().splitlines()
        lines[line - 1] = text
        (src / file).write_text("\n".join(lines) + "\n")
    return edit


def replace_field(file: str, line: int, field: int, value: str) -> Callable[[Path], None]:
    def edit(src: Path) -> None:
        lines = (src / file).read_text().splitlines()
        fields = lines[line - 1].split(",")
        fields[field] = value
        lines[line - 1] = ",".join(fields)
        (src / file).write_text("\n".join(lines) + "\n")
    return edit


def write_bytes(file: str, data: bytes) -> Callable[[Path], None]:
    return lambda src: (src / file).write_bytes(data)


def prepend(file: str, data: bytes) -> Callable[[Path], None]:
    return lambda src: (src / file).write_bytes(data + (src / file).read_bytes())


def meta(text: str) -> Callable[[Path], None]:
    return lambda src: (src / "meta.yaml").write_text(text)


def calib_text(old: str, new: str) -> Callable[[Path], None]:
    def edit(src: Path) -> None:
        text = (src / "calibration.yaml").read_text()
        assert old in text, old
        (src / "calibration.yaml").write_text(text.replace(old, new, 1))
    return edit


def calib(**changes) -> Callable[[Path], None]:
    def edit(src: Path) -> None:
        c = calibration()
        values = {k: getattr(c, k) for k in ("width", "height", "K1", "D1", "K2", "D2", "R", "T")}
        values.update(changes)
        type(c)(**values).save(src / "calibration.yaml")
    return edit


def same_force(rec: Recording, src: Path) -> None:
    """The recording's force is what force.csv holds, read here with the csv module."""
    with open(src / "force.csv", newline="", encoding="utf-8-sig") as f:
        rows = [row for row in csv.reader(f) if row][1:]
    assert rec.force.times_ns.tolist() == [int(row[0]) for row in rows]
    assert rec.force.wrench.tolist() == [[float(v) for v in row[1:]] for row in rows]


def extra_is(key: str, text: str) -> Callable[[Recording, Path], None]:
    def check(rec: Recording, src: Path) -> None:
        assert rec.metadata.extra[key] == text, rec.metadata.extra
    return check


def distortion_of(n: int) -> Callable[[Recording, Path], None]:
    def check(rec: Recording, src: Path) -> None:
        left, _ = rec.camera_infos
        assert len(left.d) == n and left.distortion_model == ("plumb_bob" if n <= 5 else "rational_polynomial")
        assert rec.stereo.baseline_mm > 0
    return check


ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
    f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n" for i in range(8))

RAW_CASES = [
    # force.csv, frames.csv, ecm_pose.csv
    raw_case("unquoted_decimal_comma", replace_field("force.csv", 10, 2, "0,011748"),
             "force.csv: line 10: 8 fields but the header has 7: a decimal comma"),
    raw_case("quoted_decimal_comma", replace_field("force.csv", 10, 2, '"0,011748"'),
             "force.csv: line 10: fy '0,011748' is not a number (a decimal comma?"),
    raw_case("semicolon_separated", lambda src: (src / "force.csv").write_text(
        (src / "force.csv").read_text().replace(",", ";")), "force.csv: fields are separated by ';'"),
    raw_case("short_row", replace_line("force.csv", 7, "1700000000000000000,1.0"),
             "force.csv: line 7: 2 fields but the header has 7"),
    raw_case("bom_in_force", prepend("force.csv", b"\xef\xbb\xbf"), None, same_force),
    raw_case("bom_in_frames", prepend("frames.csv", b"\xef\xbb\xbf"), None),
    raw_case("bom_in_pose", prepend("ecm_pose.csv", b"\xef\xbb\xbf"), None),
    raw_case("crlf_lines", lambda src: (src / "force.csv").write_bytes(
        (src / "force.csv").read_bytes().replace(b"\n", b"\r\n")), None, same_force),
    raw_case("blank_lines_then_nan", lambda src: (src / "force.csv").write_text(
        (src / "force.csv").read_text().replace("\n", "\n\n", 3).replace(
            (src / "force.csv").read_text().splitlines()[20].split(",")[3], "nan", 1)),
             "force.csv: line 24: NaN or inf value"),
    raw_case("non_utf8_value", lambda src: (src / "force.csv").write_bytes(
        (src / "force.csv").read_bytes().replace(b"\n", b"\xff\n", 4)),
             "force.csv: line 1: not UTF-8 text (byte 0xff)"),
    raw_case("latin1_byte", lambda src: (src / "force.csv").write_bytes(
        (src / "force.csv").read_bytes().replace(b"fx", b"f\xe9x", 1)),
             "force.csv: line 1: not UTF-8 text (byte 0xe9)"),
    raw_case("utf16_file", lambda src: (src / "frames.csv").write_bytes(
        (src / "frames.csv").read_text().encode("utf-16")), "frames.csv: line 1: not UTF-8 text"),
    raw_case("arabic_indic_digits", replace_field("frames.csv", 3, 1, "١٧٠٠٠٠٠٠٠٠٠٣٣٣٣٣٣٣٣"),
             "frames.csv: line 3: timestamp_ns '١٧٠٠٠٠٠٠٠٠٠٣٣٣٣٣٣٣٣' is not an integer"),
    raw_case("superscript_digit", replace_field("frames.csv", 3, 0, "1²"),
             "frames.csv: line 3: frame '1²' is not an integer"),
    raw_case("fullwidth_digits_in_force", replace_field("force.csv", 4, 1, "１.５"),
             "force.csv: line 4: fx '１.５' is not a number"),
    raw_case("underscore_digits", replace_field("frames.csv", 2, 1, "1_700_000_000_000_000_000"),
             "frames.csv: line 2: timestamp_ns '1_700_000_000_000_000_000' is not an integer"),
    raw_case("stamp_beyond_int64", replace_field("frames.csv", 7, 1, "99999999999999999999"),
             "frames.csv: line 7: timestamp_ns 99999999999999999999 is out of range"),
    raw_case("stamp_beyond_ros_time", replace_field("force.csv", 2, 0, "3000000000000000000"),
             "force.csv: line 2: timestamp_ns 3000000000000000000 is beyond ROS time"),
    raw_case("negative_frame_stamp", replace_field("frames.csv", 2, 1, "-5"),
             "frames.csv: line 2: timestamp_ns -5 is negative"),
    raw_case("negative_pose_stamp", replace_field("ecm_pose.csv", 2, 0, "-1700000000000000000"),
             "ecm_pose.csv: line 2: timestamp_ns -1700000000000000000 is negative"),
    raw_case("stamps_from_zero", lambda src: [replace_field("frames.csv", i + 2, 1, str(i * 33_333_333))(src)
                                              for i in range(6)], "force starts"),
    raw_case("nul_byte", lambda src: (src / "force.csv").write_bytes(
        (src / "force.csv").read_bytes().replace(b"\n", b"\n\x00", 1)), "force.csv: line 2:"),
    raw_case("empty_force", write_bytes("force.csv", b""), "force.csv: file is empty"),
    raw_case("header_only", write_bytes("force.csv", b"timestamp_ns,fx,fy,fz,tx,ty,tz\n"),
             "force.csv: no force samples"),
    raw_case("repeated_column", replace_line("force.csv", 1, "timestamp_ns,fx,fx,fz,tx,ty,tz"),
             "force.csv: missing column(s) fy"),
    raw_case("repeated_required_column", lambda src: (src / "force.csv").write_text("".join(
        line + (",fz\n" if i == 0 else ",0\n") for i, line in enumerate((src / "force.csv").read_text().splitlines()))),
             "force.csv: column(s) fz appear more than once in the header"),
    raw_case("spaces_in_header", replace_line("force.csv", 1,
             "timestamp_ns, fx, fy, fz, tx, ty, tz"), None, same_force),
    raw_case("binary_force", write_bytes("force.csv", bytes(range(256)) * 4), "force.csv: line 2: not UTF-8 text"),
    raw_case("force_is_a_folder", lambda src: ((src / "force.csv").unlink(), (src / "force.csv").mkdir()),
             "force.csv: file not found"),
    # calibration.yaml
    raw_case("binary_calibration", write_bytes("calibration.yaml", b"\x00\x01\xff\xfe" * 64),
             "calibration.yaml: not a readable OpenCV FileStorage YAML file"),
    raw_case("malformed_calibration", calib_text("data: [", "data: [[ 1,"),
             "calibration.yaml: not a readable OpenCV FileStorage YAML file"),
    raw_case("empty_calibration", write_bytes("calibration.yaml", b""),
             "calibration.yaml: not a readable OpenCV FileStorage YAML file"),
    raw_case("calibration_is_a_list", write_bytes("calibration.yaml", b"%YAML:1.0\n- 1\n- 2\n"),
             "calibration.yaml: not a mapping"),
    raw_case("singular_K", calib(K1=np.zeros((3, 3))),
             "calibration.yaml: K1: focal lengths fx = 0, fy = 0 must be positive"),
    raw_case("negative_fx", calib(K2=np.array([[-200.0, 0, 80], [0, 200, 64], [0, 0, 1]])),
             "calibration.yaml: K2: focal lengths fx = -200"),
    raw_case("K_last_row", calib(K1=np.array([[200.0, 0, 80], [0, 200, 64], [0, 0, 0]])),
             "calibration.yaml: K1 is not a camera matrix"),
    raw_case("nan_in_K", calib(K1=np.array([[np.nan, 0, 80], [0, 200, 64], [0, 0, 1]])),
             "calibration.yaml: calibration holds NaN or inf"),
    raw_case("three_coefficients", calib(D1=np.zeros(3)), "calibration.yaml: D1 has 3 coefficients"),
    raw_case("eight_coefficients", calib(D1=np.full(8, 1e-3), D2=np.full(8, 1e-3)), None, distortion_of(8)),
    raw_case("twelve_coefficients", calib(D1=np.full(12, 1e-4), D2=np.full(12, 1e-4)), None, distortion_of(12)),
    raw_case("fourteen_coefficients", calib(D1=np.full(14, 1e-4), D2=np.full(14, 1e-4)), None, distortion_of(14)),
    raw_case("empty_coefficient_matrix", calib(D1=np.zeros(0), D2=np.zeros(0)), "'D1' is not an OpenCV matrix"),
    raw_case("R_not_a_rotation", calib(R=np.zeros((3, 3))), "calibration.yaml: R is not a rotation matrix"),
    raw_case("width_is_text", calib_text("image_width: 160", 'image_width: "abc"'),
             "calibration.yaml: 'image_width' must be a whole number"),
    raw_case("width_not_whole", calib_text("image_width: 160", "image_width: 160.5"),
             "calibration.yaml: 'image_width' must be a whole number"),
    raw_case("K_as_plain_list", lambda src: (src / "calibration.yaml").write_text(
        (src / "calibration.yaml").read_text().replace("K1: !!opencv-matrix", "K1: [200, 0, 80, 0, 200, 64, 0, 0, 1]\n"
                                                       "K1_old: !!opencv-matrix")),
             "calibration.yaml: 'K1' is not an OpenCV matrix"),
    raw_case("matrix_data_short", lambda src: (src / "calibration.yaml").write_text(re.sub(
        r"(K1: !!opencv-matrix\n(?:.*\n){3}\s*data: \[)\s*[^,]+,", r"\1", (src / "calibration.yaml").read_text())),
             "calibration.yaml: 'K1' is not an OpenCV matrix"),
    raw_case("units_a_number", calib_text('units: mm', 'units: 5'), "calibration.yaml: 'units' must be text"),
    raw_case("latin1_comment", lambda src: (src / "calibration.yaml").write_bytes(
        (src / "calibration.yaml").read_bytes() + b"# calibr\xe9\n"), None),
    # meta.yaml
    raw_case("orientation_text", meta("orientation_deg: ninety\n"), "meta.yaml: 'orientation_deg' must be a number"),
    raw_case("orientation_list", meta("orientation_deg: [90]\n"), "meta.yaml: 'orientation_deg' must be a number"),
    raw_case("orientation_nan", meta("orientation_deg: .nan\n"), "meta.yaml: 'orientation_deg' must be a number"),
    raw_case("orientation_quoted_number", meta("orientation_deg: '45'\n"), None,
             lambda rec, src: rec.metadata.orientation_deg == 45.0 or pytest.fail("orientation")),
    raw_case("gravity_two_numbers", meta("gravity_up_world: [0, 1]\n"),
             "meta.yaml: 'gravity_up_world' must be 3 numbers"),
    raw_case("gravity_zero", meta("gravity_up_world: [0, 0, 0]\n"), "of non-zero length"),
    raw_case("gravity_text", meta("gravity_up_world: up\n"), "meta.yaml: 'gravity_up_world' must be 3 numbers"),
    raw_case("gravity_inf", meta("gravity_up_world: [0, 0, .inf]\n"),
             "meta.yaml: 'gravity_up_world' must be 3 numbers"),
    raw_case("gravity_bools", meta("gravity_up_world: [true, false, true]\n"), "'gravity_up_world' must be 3 numbers"),
    raw_case("prompt_box_free_text", meta("prompt_box: the tissue in the middle\n"),
             "meta.yaml: 'prompt_box' must be 4 numbers [x0, y0, x1, y1]"),
    raw_case("prompt_box_reversed", meta("prompt_box: [100, 10, 50, 60]\n"), "must have x0 < x1 and y0 < y1"),
    raw_case("prompt_box_outside", meta("prompt_box: [0, 0, 1000, 100]\n"), "lies outside the 160x128 image"),
    raw_case("prompt_box_three", meta("prompt_box: [1, 2, 3]\n"), "'prompt_box' must be 4 numbers"),
    raw_case("prompt_box_list", meta("prompt_box: [10, 20, 100, 90]\n"), None, extra_is("prompt_box",
             "[10, 20, 100, 90]")),
    raw_case("prompt_box_text", meta("prompt_box: '10,20,100,90'\n"), None, extra_is("prompt_box", "10,20,100,90")),
    raw_case("study_a_list", meta("study: [a, b]\n"), "meta.yaml: 'study' must be text, not a list"),
    raw_case("split_a_mapping", meta("split: {train: 1}\n"), "meta.yaml: 'split' must be text, not a mapping"),
    raw_case("non_utf8_meta", write_bytes("meta.yaml", b"study: gl\xf6ve\n"), "meta.yaml: not UTF-8 text"),
    raw_case("bom_meta", write_bytes("meta.yaml", b"\xef\xbb\xbfstudy: glove\n"), None,
             lambda rec, src: rec.metadata.study == "glove" or pytest.fail("study")),
    raw_case("meta_a_list", meta("- a\n- b\n"), "meta.yaml: must be a mapping"),
    raw_case("meta_invalid_yaml", meta("study: [glove\n"), "meta.yaml: not valid YAML"),
    raw_case("meta_python_tag", meta("x: !!python/object/apply:os.system ['true']\n"), "meta.yaml: not valid YAML"),
    raw_case("meta_key_not_text", meta("1: one\n"), "meta.yaml: key 1 is not text"),
    raw_case("meta_values_as_json", meta("synthetic: true\nlevels: [1, 2.5]\nday: 2024-05-01\nn: 3\nnothing:\n"), None,
             lambda rec, src: [extra_is(k, v)(rec, src) for k, v in (("synthetic", "true"), ("levels", "[1, 2.5]"),
                                                                     ("day", "2024-05-01"), ("n", "3"),
                                                                     ("nothing", "null"))]),
    raw_case("meta_source_kept", meta("source: hamlyn\n"), None,
             lambda rec, src: [extra_is("meta_source", "hamlyn")(rec, src),
                               rec.metadata.source == str(src.resolve()) or pytest.fail("source")]),
    raw_case("meta_source_taken", meta("source: a\nmeta_source: b\n"), "'meta_source' is taken"),
    raw_case("meta_alias_bomb", meta(ALIAS_BOMB), "holds too much (more than 10000 values"),
    raw_case("meta_nan_extra", meta("x: .nan\n"), "meta.yaml: 'x' holds nan, which JSON cannot store"),
    raw_case("meta_binary", meta("x: !!binary aGVsbG8=\n"), "meta.yaml: 'x' holds binary data"),
    raw_case("meta_empty_study", meta("study:\nid: 7\n"), None,
             lambda rec, src: (rec.metadata.study, rec.metadata.recording_id) == ("", "7") or pytest.fail("meta")),
    # images, videos
    raw_case("zero_byte_image", write_bytes("left/000002.png", b""), "left/000002.png: image cannot be decoded"),
    raw_case("image_folder_named_png", lambda src: ((src / "right" / "000003.png").unlink(),
                                                    (src / "right" / "000003.png").mkdir()), "000003.png"),
    raw_case("garbage_video", lambda src: [shutil.rmtree(src / "left"), shutil.rmtree(src / "right"),
                                           (src / "stereo.mp4").write_bytes(os.urandom(4096))],
             "stereo.mp4: video cannot be opened"),
    # options and outputs
    raw_case("quality_zero", lambda src: None, "--quality: JPEG quality must be 1-100", args=["--quality", "0"]),
    raw_case("force_gap_negative", lambda src: None, "--force-gap-ms: must be a positive number",
             args=["--force-gap-ms", "-5"]),
    raw_case("force_gap_nan", lambda src: None, "--force-gap-ms: must be a positive number", args=["--force-gap-ms",
             "nan"]),
    raw_case("output_is_force_csv", lambda src: None,
             "write the output elsewhere", args=["--overwrite"], out=lambda src: src / "force.csv"),
    raw_case("output_is_an_image", lambda src: None, "is inside the input folder", args=["--overwrite"],
             out=lambda src: src / "left" / "000001.png"),
    raw_case("output_is_the_folder", lambda src: None, "is the input", args=["--overwrite"], out=lambda src: src),
    raw_case("output_folder_missing", lambda src: None, "output folder does not exist",
             out=lambda src: src.parent / "nowhere" / "rec.mcap"),
    raw_case("output_a_folder", lambda src: (src.parent / "out" / "rec.mcap").mkdir(parents=True), "output exists"),
]


# -- bags --------------------------------------------------------------------------------------------
def bag_case(name: str, spec: BagSpec, expect: str | None, edit=None, args=(), out=None, check=None) -> Case:
    def build(tmp: Path):
        src = tmp / ("bag" if spec.ros2 else "x.bag")
        write_bag(src, spec)
        if edit is not None:
            edit(src)
        return src, list(args(src) if callable(args) else args), out(src) if out else None
    return Case(name, build, expect, check)


def truncate(fraction: float) -> Callable[[Path], None]:
    def edit(src: Path) -> None:
        data = src.read_bytes()
        src.write_bytes(data[:int(len(data) * fraction)])
    return edit


BAG_CASES = [
    bag_case("negative_stamps_ros2", BagSpec(ros2=True, frames=4, force_shift_ns=-BAG_T0_NS - 10**9),
             "/netft_data: a message has header.stamp -"),
    bag_case("singular_camera_info_K", BagSpec(frames=4, camera_k=(0.0,) * 9), "K has no positive focal length"),
    bag_case("three_coefficient_D", BagSpec(frames=4, camera_d=(0.1, 0.0, 0.0)), "D has 3 coefficients"),
    bag_case("garbage_force_payloads", BagSpec(ros2=True, frames=4, force_payload=b"{\"fx\": 1}"),
             "/netft_data: message cannot be decoded"),
    bag_case("truncated_ros1", BagSpec(frames=6), "x.bag", edit=truncate(0.6)),
    bag_case("empty_ros1", BagSpec(frames=2), "x.bag: cannot read the bag", edit=lambda src: src.write_bytes(b"")),
    bag_case("garbage_metadata", BagSpec(ros2=True, frames=2), "cannot read the bag",
             edit=lambda src: (src / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")),
    bag_case("30hz_force_one_dropped", BagSpec(frames=20, force_step_ns=33_000_000, drop_force=(8,)), None,
             check=lambda rec, src: np.median(np.diff(rec.force.times_ns)) == 33_000_000 or pytest.fail("force")),
    bag_case("output_is_the_bag", BagSpec(frames=2), "is the input", args=["--overwrite"], out=lambda src: src),
    bag_case("output_inside_ros2_bag", BagSpec(ros2=True, storage=StoragePlugin.SQLITE3, frames=2),
             "is inside the input folder", args=["--overwrite"], out=lambda src: src / "metadata.yaml"),
    bag_case("pair_tolerance_nan", BagSpec(frames=2), "--pair-tolerance-ms: must be a number",
             args=["--pair-tolerance-ms", "nan"]),
    bag_case("calibration_is_the_output", BagSpec(frames=2), "is the input",
             edit=lambda src: calibration(64, 48).save(src.parent / "calib.yaml"),
             args=lambda src: ["--overwrite", "--calibration", str(src.parent / "calib.yaml")],
             out=lambda src: src.parent / "calib.yaml"),
]


@pytest.mark.parametrize("case", RAW_CASES + BAG_CASES, ids=lambda c: c.name)
def test_corpus_case_ends_cleanly(tmp_path, capsys, case):
    src, args, out = case.build(tmp_path)
    if out is None:
        out = tmp_path / "out" / "rec.mcap"
        out.parent.mkdir(exist_ok=True)
    before = tree_digest(src)
    out_before = tree_digest(out) if out.exists() else None
    leftovers_before = set(out.parent.iterdir()) if out.parent.is_dir() else set()
    code = main(["convert", "--quiet", "--format", "png", *args, str(src), str(out)])
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and "internal error" not in err, err
    assert tree_digest(src) == before, "an input was modified"
    if case.expect is None:
        assert code == 0, err
        rec = Recording.open(out)
        assert rec.problems == []
        if case.check is not None:
            case.check(rec, src)
        return
    assert code == 1, err
    lines = [line for line in err.splitlines() if not line.startswith("warning:")]
    assert len(lines) == 1 and case.expect in lines[0], err
    assert (tree_digest(out) if out.exists() else None) == out_before, "a refused output was changed"
    if out.parent.is_dir():
        assert set(out.parent.iterdir()) == leftovers_before, "output or temporary left behind"


# -- permissions -------------------------------------------------------------------------------------
PERMISSION_CASES = [
    # (name, file made unreadable or folder made read-only, expected piece of the one line)
    ("unreadable_force", "force.csv", "force.csv: Permission denied"),
    ("unreadable_calibration", "calibration.yaml", "calibration.yaml: Permission denied"),
    ("unreadable_meta", "meta.yaml", "meta.yaml: Permission denied"),
    ("unreadable_image", "left/000003.png", "000003.png: Permission denied"),
    ("unreadable_left_folder", "left", "left: Permission denied"),
    ("read_only_output_folder", "OUT", "rec.mcap: cannot be written (Permission denied)"),
]


def test_corpus_permissions(tmp_path):
    """Unreadable inputs and an output folder we may not write, as a user without root's file
    permission override (`setpriv` drops CAP_DAC_OVERRIDE for the child)."""
    if shutil.which("setpriv") is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv to drop the permission override")
    runs = []
    for name, target, expected in PERMISSION_CASES:
        src = make_raw(tmp_path / name / "rec", n=4)
        out_dir = tmp_path / name / "out"
        out_dir.mkdir()
        locked = out_dir if target == "OUT" else src / target
        locked.chmod(0o555 if target == "OUT" else 0)
        runs.append((name, expected, [str(src), str(out_dir / "rec.mcap")], out_dir, src, locked))
    script = ("import json, sys, contextlib, io\nfrom vfdata.cli import main\nresults = []\n"
              "for args in json.loads(sys.argv[1]):\n    err = io.StringIO()\n"
              "    with contextlib.redirect_stderr(err):\n        code = main(['convert', '--quiet', *args])\n"
              "    results.append([code, err.getvalue()])\nprint(json.dumps(results))\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(["setpriv", "--bounding-set=-dac_override,-dac_read_search", sys.executable, "-c", script,
                           json.dumps([r[2] for r in runs])], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    for (name, expected, _args, out_dir, _src, locked), (code, err) in zip(runs, json.loads(done.stdout), strict=True):
        locked.chmod(0o755 if locked.is_dir() else 0o644)
        assert code == 1 and len(err.strip().splitlines()) == 1 and expected in err, (name, err)
        assert "Traceback" not in err and list(out_dir.iterdir()) == [], name
