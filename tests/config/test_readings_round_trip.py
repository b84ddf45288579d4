"""The readings CSV contract: exact round trip, extra columns ignored, optional temperature."""

from __future__ import annotations

import numpy as np

from labcal.analysis.readings import Readings
from labcal.config.readings_csv import read_readings, write_readings


def test_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(2)
    n = 20
    readings = Readings(
        replicate=np.repeat([1, 2], n // 2), y_deg=np.tile([0.0, 180.0], n // 2),
        u_deg=np.zeros(n), pitch_deg=rng.integers(-180, 360, n).astype(float),
        roll_deg=rng.integers(0, 360, n).astype(float), volts=rng.normal(0, 5, (n, 3)),
        temp_c=None,
    )
    write_readings(tmp_path / "r.csv", readings)
    back = read_readings(tmp_path / "r.csv")
    for name in ("replicate", "y_deg", "u_deg", "pitch_deg", "roll_deg", "volts"):
        assert np.array_equal(getattr(back, name), getattr(readings, name)), name
    assert back.temp_c is None
    header = (tmp_path / "r.csv").read_text().splitlines()[0]
    assert header == "replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz"  # docs/design.md §5


def test_extra_columns_in_any_order_are_ignored_and_temperature_is_read(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text(
        "note,vz,vy,vx,roll_deg,pitch_deg,u_deg,y_deg,replicate,temp_c\n"
        "first,1.0,0.5,0.25,90,-30,180,0,2,21.5\n"
    )
    r = read_readings(path)
    assert np.array_equal(r.volts, [[0.25, 0.5, 1.0]])
    assert r.pitch_deg[0] == -30 and r.roll_deg[0] == 90 and r.u_deg[0] == 180 and r.replicate[0] == 2
    assert r.temp_c is not None and r.temp_c[0] == 21.5
