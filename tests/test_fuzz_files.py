"""File readers under malformed input: .mcrec recordings and plain CSV (convert,
triangulate, --replay), C3D takes and mocapd.toml values end with one UserError naming the
file (and the line), never another exception; good files still read exactly (issue 30)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibkit.core.errors import UserError
from calibkit.core.recording import FORMAT, load_observations

ROOT = Path(__file__).resolve().parents[1]
HEADER = {"format": FORMAT, "version": 1, "fps": 100.0, "meta": {},
          "cameras": [{"name": "cam0", "size": [640, 480]}, {"name": "cam1", "size": [640, 480]}]}
FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def _good_record(k: int, n: int) -> dict:
    return {"f": k, "c": k % 2, "t": 1_700_000_000_000_000_000 + k,
            "b": [[10.0 + j, 20.5, 3.0, 200.0] for j in range(n)], "m": list(range(n))}


# what breaks a record, each a function of a good record -> a bad one
BREAKS = {
    "missing key": lambda r: {k: v for k, v in r.items() if k != "t"},
    "frame as text": lambda r: {**r, "f": "12"},
    "fractional frame": lambda r: {**r, "f": 1.5},
    "camera beyond the header": lambda r: {**r, "c": 2},
    "negative camera": lambda r: {**r, "c": -1},
    "blobs not a list": lambda r: {**r, "b": {"u": 1}},
    "short blob": lambda r: {**r, "b": [[1.0, 2.0]], "m": [0]},
    "blob with text": lambda r: {**r, "b": [[1.0, "x", 3.0, 4.0]], "m": [0]},
    "NaN blob": lambda r: {**r, "b": [[float("nan"), 2.0, 3.0, 4.0]], "m": [0]},
    "infinite blob": lambda r: {**r, "b": [[1.0, float("inf"), 3.0, 4.0]], "m": [0]},
    "huge number": lambda r: {**r, "b": [[10 ** 400, 2.0, 3.0, 4.0]], "m": [0]},
    "markers of another length": lambda r: {**r, "m": [0, 1, 2, 3, 4, 5, 6]},
    "a list, not a record": lambda r: [1, 2, 3],
    "time beyond 64 bits": lambda r: {**r, "t": 2 ** 70},
    "truth without positions": lambda r: {"truth": 3, "m": [1]},
    "truth of another length": lambda r: {"truth": 3, "m": [1, 2], "xyz": [[0, 0, 0]]},
    "truth with NaN": lambda r: {"truth": 3, "m": [1], "xyz": [[0, float("nan"), 0]]},
}


def _write(path: Path, header, records, tail: str = "") -> None:
    lines = [json.dumps(header)] + [json.dumps(r) for r in records]
    path.write_text("\n".join(lines) + "\n" + tail, encoding="utf-8")


@FUZZ
@given(counts=st.lists(st.integers(0, 4), min_size=1, max_size=8), data=st.data())
def test_a_malformed_record_names_the_file_and_its_line(tmp_path, counts, data):
    records = [_good_record(k, n) for k, n in enumerate(counts)]
    path = tmp_path / "take.mcrec"
    _write(path, HEADER, records)
    obs, _ = load_observations(path)  # the good file reads exactly
    assert len(obs) == sum(counts)
    assert obs.t_ns.tolist() == [1_700_000_000_000_000_000 + k
                                 for k, n in enumerate(counts) for _ in range(n)]
    which = data.draw(st.integers(0, len(records) - 1))
    kind = data.draw(st.sampled_from(sorted(BREAKS)))
    records[which] = BREAKS[kind](records[which])
    _write(path, HEADER, records)
    with pytest.raises(UserError) as err:
        load_observations(path)
    assert str(err.value).startswith(f"{path}:{which + 2}: "), (kind, str(err.value))


@FUZZ
@given(records=st.lists(st.one_of(
    st.dictionaries(st.sampled_from(["f", "c", "t", "b", "m", "truth", "xyz"]),
                    st.recursive(st.none() | st.booleans() | st.integers() | st.floats()
                                 | st.text(max_size=4),
                                 lambda c: st.lists(c, max_size=5), max_leaves=12)),
    st.integers(), st.text(max_size=5)), max_size=6),
    header=st.one_of(st.just(HEADER), st.dictionaries(
        st.sampled_from(["format", "version", "cameras", "fps", "meta"]),
        st.one_of(st.just(FORMAT), st.integers(), st.floats(), st.text(max_size=3),
                  st.lists(st.dictionaries(st.sampled_from(["name", "size"]),
                                           st.one_of(st.text(max_size=3),
                                                     st.lists(st.integers(), max_size=3))),
                           max_size=2)))))
def test_any_json_records_give_observations_or_one_user_error(tmp_path, records, header):
    path = tmp_path / "any.mcrec"
    _write(path, header, records)
    try:
        load_observations(path)
    except UserError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)


@FUZZ
@given(data=st.binary(max_size=400))
def test_random_bytes_are_no_recording(tmp_path, data):
    path = tmp_path / "junk.mcrec"
    path.write_bytes(data)
    with pytest.raises(UserError):
        load_observations(path)
    path.write_bytes((json.dumps(HEADER) + "\n").encode() + data + b"\n{}\n")
    with pytest.raises(UserError):  # a broken line followed by another: damaged
        load_observations(path)


def test_a_torn_last_line_is_still_skipped_silently(tmp_path):
    records = [_good_record(k, 2) for k in range(5)]
    path = tmp_path / "killed.mcrec"
    torn = json.dumps(_good_record(5, 3))[:17]
    _write(path, HEADER, records, tail=torn)
    obs, _ = load_observations(path)
    assert len(obs) == 10 and obs.frame.max() == 4
    path.write_bytes(path.read_bytes() + b"\xff\xfe")  # torn inside a UTF-8 sequence
    assert len(load_observations(path)[0]) == 10


# ---- plain CSV -------------------------------------------------------------------------------

CSV_HEAD = "frame,camera,t_ns,u,v,area,peak\n"


def _csv_row(k: int) -> list[str]:
    return [str(k), f"cam{k % 2}", str(1_700_000_000_000_000_123 + k), "10.25", "20.5", "3",
            "200"]


CELL_BREAKS = {0: ["1.5", "x", "", "nan", "1e400"], 2: ["inf", "abc", "1" * 30],
               3: ["nan", "inf", "-inf", "u", "1e999"], 5: ["", "NaN"], 6: ["infinity", "#"]}


@FUZZ
@given(n=st.integers(1, 8), data=st.data())
def test_a_bad_csv_cell_names_its_line_and_column(tmp_path, n, data):
    rows = [_csv_row(k) for k in range(n)]
    path = tmp_path / "obs.csv"
    path.write_text(CSV_HEAD + "".join(",".join(r) + "\n" for r in rows), encoding="utf-8")
    obs, _ = load_observations(path)
    # whole numbers read exactly: the last digits of a time since 1970 in ns are kept
    assert obs.t_ns.tolist() == [1_700_000_000_000_000_123 + k for k in range(n)]
    np.testing.assert_array_equal(obs.uv, [[10.25, 20.5]] * n)
    which = data.draw(st.integers(0, n - 1))
    col = data.draw(st.sampled_from(sorted(CELL_BREAKS)))
    rows[which][col] = data.draw(st.sampled_from(CELL_BREAKS[col]))
    path.write_text(CSV_HEAD + "".join(",".join(r) + "\n" for r in rows), encoding="utf-8")
    with pytest.raises(UserError, match=rf"^{path}: line {which + 2}, column '"):
        load_observations(path)


@FUZZ
@given(body=st.binary(max_size=300))
def test_any_csv_bytes_give_observations_or_one_user_error(tmp_path, body):
    path = tmp_path / "any.csv"
    path.write_bytes(CSV_HEAD.encode() + body)
    try:
        obs, _ = load_observations(path)
    except UserError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)
    else:
        assert np.isfinite(obs.uv).all() and np.isfinite(obs.area).all()


def test_convert_ends_a_malformed_recording_with_one_line(tmp_path):
    records = [_good_record(k, 2) for k in range(4)]
    records[2] = BREAKS["missing key"](records[2])
    src = tmp_path / "bad.mcrec"
    _write(src, HEADER, records)
    before = src.read_bytes()
    r = subprocess.run([sys.executable, "-m", "calibkit.cli", "convert", str(src), "--out",
                        str(tmp_path / "out.csv")], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert [ln for ln in r.stderr.splitlines() if ln.strip()] == [
        f"calibkit: error: {src}:4: malformed record (a blobs record needs \"t\")"], r.stderr
    assert src.read_bytes() == before and not (tmp_path / "out.csv").exists()


# ---- C3D and mocapd.toml ---------------------------------------------------------------------

C3D = (ROOT / "fixtures" / "cmu_c3d" / "85_02.c3d").read_bytes()


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, 24000), changes=st.lists(
    st.tuples(st.integers(0, 12000), st.integers(0, 255)), max_size=6))
def test_a_damaged_c3d_gives_a_take_or_one_user_error(tmp_path, cut, changes):
    """The CMU take cut short (the c3d package then stops inside a frame) and with bytes of
    its header and parameters changed."""
    from daemon.formats.c3dio import read_c3d

    data = bytearray(C3D[:cut])
    for at, value in changes:
        if at < len(data):
            data[at] = value
    path = tmp_path / "take.c3d"
    path.write_bytes(bytes(data))
    try:
        take = read_c3d(path)
    except UserError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
    else:
        assert take.rate_hz > 0 and take.xyz_m.shape[1] == len(take.labels)


def test_a_c3d_header_claiming_billions_of_frames_is_refused_before_allocating(tmp_path):
    """65535 frames of 41 points in the header's last-frame word (words 4 and 5 are the
    first and last frame), 810 in the file: refused before 65535 x 41 x 3 floats."""
    from daemon.formats.c3dio import read_c3d

    data = bytearray(C3D)
    assert int.from_bytes(data[6:8], "little") == 1 and data[8:10] == (810).to_bytes(2, "little")
    data[8:10] = (65535).to_bytes(2, "little")
    path = tmp_path / "big.c3d"
    path.write_bytes(bytes(data))
    with pytest.raises(UserError, match="the header says 65535 frames of 41 points"):
        read_c3d(path)


CONFIG_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10, 70000),
                          st.sampled_from([10 ** 30, -(10 ** 30)]), st.floats(),
                          st.text(max_size=12),
                          st.sampled_from(["127.0.0.1", "0.0.0.0", "239.255.42.99", "auto", "z",
                                           "udpout:127.0.0.1:14550", "greedy"]),
                          st.lists(st.integers(), max_size=3))
CONFIG_KEYS = ["fps", "mode", "interface", "command_port", "data_port", "group", "rate_hz",
               "up_axis", "record_from", "record_max_s", "address", "device", "body", "name",
               "id", "markers", "cameras", "bodies", "dropout", "source", "threshold",
               "max_lag_ms", "listen", "connect", "rig"]
CONFIG_TABLES = ["pipeline", "tracker", "rigid", "sim", "natnet", "vrpn", "udp", "serial",
                 "mavlink", "camera", "replay", "zenoh", "rigid_body", "record_min_free_mb"]


@settings(max_examples=400, deadline=None)
@given(data=st.dictionaries(st.sampled_from(CONFIG_TABLES), st.one_of(
    CONFIG_VALUES, st.dictionaries(st.sampled_from(CONFIG_KEYS), CONFIG_VALUES, max_size=4),
    st.lists(st.dictionaries(st.sampled_from(CONFIG_KEYS), CONFIG_VALUES, max_size=4),
             max_size=2)), max_size=3))
def test_any_configuration_values_give_a_config_or_one_user_error(data):
    from daemon.config.mocapd import parse_config

    try:
        cfg = parse_config(data)
    except UserError as exc:
        assert "\n" not in str(exc)
    else:
        assert np.isfinite(cfg.fps) and cfg.fps > 0


def test_nan_in_a_configuration_is_refused():
    from daemon.config.mocapd import parse_config

    for table, key in (("pipeline", "fps"), ("natnet", "rate_hz"), ("natnet", "record_max_s")):
        with pytest.raises(UserError, match=f"{table}.{key}: expected a number, got nan"):
            parse_config({table: {key: float("nan")}})
