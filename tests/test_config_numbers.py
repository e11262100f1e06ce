"""mocapd.toml numbers: inf, -inf, nan and out-of-range integers are refused, naming the key.

Why: TOML spells `inf` and `nan` as numbers, and both pass a range check that has only a
lower bound (nan compares false with everything, inf is above any floor), so a key such as
`rate_hz = inf` or `record_min_free_mb = nan` used to be taken as it was (issue 30). Each
case here was accepted before the check; now `mocapd start` ends with one line naming the
file and the key, exit 2, and opens nothing.
"""

from __future__ import annotations

import pytest

from calibkit.core.errors import UserError
from daemon.config.mocapd import load_config

# (TOML text with VALUE where the number goes, the key the error must name): keys whose
# check has a lower bound only, one per table kind that has them
UNBOUNDED = [
    ("record_min_free_mb = VALUE\n", "record_min_free_mb"),
    ("[tracker]\ngate_px = VALUE\n", "tracker.gate_px"),
    ("[tracker]\nmerge_m = VALUE\n", "tracker.merge_m"),
    ("[rigid]\ndistance_tol_m = VALUE\n", "rigid.distance_tol_m"),
    ("[[udp]]\naddress = '127.0.0.1:9870'\nrate_hz = VALUE\n", "udp[0].rate_hz"),
    ("[[serial]]\ndevice = '/dev/ttyUSB0'\nrate_hz = VALUE\n", "serial[0].rate_hz"),
    ("[natnet]\nrate_hz = VALUE\n", "natnet.rate_hz"),
    ("[[vrpn]]\naddress = '127.0.0.1:3883'\nrate_hz = VALUE\n", "vrpn[0].rate_hz"),
    ("[[camera]]\nname = 'c'\nsource = '0'\nmin_area = VALUE\n", "camera[0].min_area"),
    ("[[camera]]\nname = 'c'\nsource = '0'\nmax_area = VALUE\n", "camera[0].max_area"),
]


@pytest.mark.parametrize("value", ["inf", "+inf", "-inf", "nan"])
@pytest.mark.parametrize(("text", "key"), UNBOUNDED)
def test_non_finite_numbers_are_refused_naming_the_key(tmp_path, text, key, value):
    path = tmp_path / "mocapd.toml"
    path.write_text(text.replace("VALUE", value))
    with pytest.raises(UserError) as err:
        load_config(path)
    line = str(err.value)
    assert "\n" not in line
    assert line.startswith(f"{path}: {key}: ")
    # -inf may be refused by the lower bound instead; inf and nan only by the new check
    if value != "-inf":
        assert "expected a number, got" in line and value.lstrip("+") in line


@pytest.mark.parametrize(("text", "key"), UNBOUNDED[:3])
def test_the_same_keys_take_a_finite_value(tmp_path, text, key):
    """The check refuses what is not a number, not the keys: 1.5 still loads."""
    path = tmp_path / "mocapd.toml"
    path.write_text(text.replace("VALUE", "1.5"))
    cfg = load_config(path)
    table, _, name = key.rpartition(".")
    got = getattr(getattr(cfg, table), name) if table else getattr(cfg, name)
    assert got == 1.5


def test_a_robot_start_of_nan_or_inf_is_refused(tmp_path):
    """[sim.robot] start is a list checked by hand: its yaw had no range check at all."""
    for start in ("[0.0, 0.0, nan]", "[0.0, 0.0, inf]", "[nan, 0.0, 0.0]"):
        path = tmp_path / "mocapd.toml"
        path.write_text(f"[sim.robot]\nport = 9000\nstart = {start}\n")
        with pytest.raises(UserError, match=r"sim\.robot\.start: expected \[x, y, yaw_deg\]"):
            load_config(path)


def test_an_integer_beyond_64_bits_is_refused(tmp_path):
    """TOML integers are 64-bit; Python's parser reads longer ones, which numba and numpy
    cannot hold (a tracker count of 2**70 overflowed later, with a traceback)."""
    path = tmp_path / "mocapd.toml"
    path.write_text(f"[tracker]\nmax_missing = {2**70}\n")
    with pytest.raises(UserError, match=r"tracker\.max_missing: expected a number, got"):
        load_config(path)


@pytest.mark.parametrize("value", ["inf", "nan"])
def test_mocapd_start_ends_with_one_line(tmp_path, start_refused, value):
    path = tmp_path / "mocapd.toml"
    path.write_text(f"[[udp]]\naddress = '127.0.0.1:9870'\nrate_hz = {value}\n")
    line = start_refused(path)
    assert str(path) in line and "udp[0].rate_hz" in line and value in line
