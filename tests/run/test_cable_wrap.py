"""Cable wrap: tables without slip rings keep their accumulated rotation from
home within ±cable_wrap_deg, over a whole run and across a resume; a plan that cannot is refused
before anything moves. The windings are checked against the emulators' own record of where their
tables turned (`SimAxis.record`: the unwrapped angle at every start and end of a move), not
against what labcal believes."""

from __future__ import annotations

import json

import pytest
from cli import cli
from emulators import no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import StationFile
from labcal.devices.winding import Reach, locate, plan_windings
from labcal.errors import LabcalError
from labcal.sim.emulation import Emulation

EMULATE = ["--emulate", "--time-scale", "1000", "--no-report"]
WRAP = 360.0  # the default cable wrap of a station's table and of the simulated rig
STEP_DEG = 1e-3  # an AZ drive at 1000 steps/° reads the table to one step


@pytest.fixture
def emulations(monkeypatch):
    """Every Emulation a command starts in this test, kept for its tables' records."""
    made: list[Emulation] = []
    start = Emulation.__init__

    def keep(self, *args, **kwargs):
        start(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(Emulation, "__init__", keep)
    return made


def extremes(emulation: Emulation, table: str) -> tuple[float, float]:
    angles = [angle for _, angle in emulation.rig.axis(table).record]
    return min(angles), max(angles)


def test_the_nearest_equivalent_within_the_reach_is_the_shortest_way_while_it_fits():
    wrap = Reach.of(360.0)
    assert wrap.nearest(350.0, 0.0) == -10.0  # 10° back, not 350° forwards
    assert wrap.nearest(300.0, -340.0) == -60.0  # 80° back would end at -420°: 280° forwards instead
    assert wrap.nearest(0.0, 350.0) == 360.0  # on the edge is within
    assert wrap.nearest(180.0, 0.0) == -180.0  # half a turn either way: one rule, the same every time
    assert Reach.of(90.0).nearest(180.0, 0.0) is None
    assert Reach.of(360.0, (-100.0, 280.0)) == Reach(-100.0, 280.0)
    assert Reach.of(None).nearest(350.0, 700.0) == 710.0  # slip rings: the shortest way, turns and all


def test_a_table_stopped_mid_move_is_placed_on_its_journaled_move():
    """The position read back says where a table is within a turn; the last journaled move says
    which turn: stopped at 160° on its way from -170° to -350°, the table is at -200°, where the
    nearest equivalent to home (160°) would be a turn off."""
    assert locate(160.0, (-170.0, -350.0), Reach.of(360.0)) == -200.0
    assert locate(0.0, (-270.0, -360.0), Reach.of(360.0)) == -360.0  # arrived
    assert locate(90.0, (-270.0, -360.0), Reach.of(360.0)) == -270.0  # never left
    assert locate(45.0, None, Reach.of(360.0)) == 45.0  # no move journaled: the turn nearest home
    assert locate(300.0, (10.0, 20.0), Reach.of(360.0)) == -60.0  # moved by hand: nearest its target


def test_a_plan_needing_more_than_the_wrap_is_refused_by_the_planner():
    reaches = (Reach.of(360.0), Reach.of(90.0))
    assert plan_windings([(0, 0), (0, 90), (0, 270)], reaches) == [(0, 0), (0, 90), (0, -90)]
    with pytest.raises(LabcalError, match=r"^plan refused before any motion: the roll table cannot reach "
                                          r"180° within its cable wrap and limits \(±90° from home\)"):
        plan_windings([(0, 0), (0, 90), (0, 180)], reaches)


def test_a_station_whose_roll_cables_cannot_reach_the_plan_is_refused_before_anything_moves(
        tmp_path, capsys, emulations, no_leaks):  # noqa: F811
    station = private_file("az-modbus-tcp", tmp_path)
    station.write_text(station.read_text().replace("[roll]\n", "[roll]\ncable_wrap_deg = 90\n"))
    code, _, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--yes",
                       "--out", str(tmp_path / "run"))
    assert code == 2
    assert err.count("\n") == 1 and "plan refused before any motion: roll" in err, err
    assert "180° is beyond its cable wrap (±90° from home)" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()  # no run was started
    (emulation,) = emulations
    for table in ("pitch", "roll"):
        assert emulation.rig.axis(table).travel_deg == 0  # nothing moved, not even a homing


def test_a_simulated_rig_whose_cables_cannot_reach_the_plan_is_refused(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text("cable_wrap_deg = 100\n")
    code, _, err = cli(capsys, "run", "--sim", "--rig", str(rig), "--yes", "--out", str(tmp_path / "run"),
                       "--db", str(tmp_path / "lab.sqlite"))
    assert code == 2 and err.count("\n") == 1, err
    assert ("plan refused before any motion: the roll table cannot reach 180° within its cable wrap and "
            "limits (±100° from home); change the plan, or give the roll table a larger cable_wrap") in err
    assert not (tmp_path / "run").exists()


def test_the_station_keys_are_slip_ring_or_cable_wrap(tmp_path):
    text = private_file("az-modbus-tcp", tmp_path).read_text()
    assert StationFile.model_validate(_toml(text)).roll.wrap_deg == WRAP  # the default
    ringed = _toml(text.replace("[roll]\n", "[roll]\nslip_ring = true\n"))
    assert StationFile.model_validate(ringed).roll.wrap_deg is None
    both = _toml(text.replace("[roll]\n", "[roll]\nslip_ring = true\ncable_wrap_deg = 720\n"))
    with pytest.raises(ValueError, match="give slip_ring = true or cable_wrap_deg, not both"):
        StationFile.model_validate(both)


def _toml(text: str) -> dict:
    import tomllib

    return tomllib.loads(text)


@pytest.mark.parametrize("station", ["az-modbus-tcp", "smc100-serial"])
def test_an_emulated_run_keeps_every_table_within_its_cable_wrap(station, tmp_path, capsys, emulations,
                                                               no_leaks):  # noqa: F811
    """Four mounts of 16 points whose rolls go round by quarter turns: the shortest way round every
    time wound the roll table eight turns (−2790°) on the simulated rig. The AZ drives keep their
    wrap setting (no turns in their coordinates: labcal says FWD or RVS); the SMC100 stages count
    turns, and the pitch stage has soft limits [-100°, 280°] as well."""
    code, out, err = cli(capsys, "run", "--station", str(private_file(station, tmp_path)), *EMULATE, "--yes",
                         "--out", str(tmp_path / "run"), "--json")
    assert code == 0, err
    assert json.loads(out)["points"] == 64
    (emulation,) = emulations
    low, high = extremes(emulation, "roll")
    assert -WRAP - STEP_DEG <= low and high <= WRAP + STEP_DEG, (low, high)
    assert high - low >= 360.0  # the rolls need a turn and more of cable: it was used, both ways round
    low, high = extremes(emulation, "pitch")
    assert -WRAP - STEP_DEG <= low and high <= WRAP + STEP_DEG, (low, high)
    if station == "smc100-serial":
        assert -100.0 - STEP_DEG <= low and high <= 280.0 + STEP_DEG


def test_a_run_stopped_mid_way_resumes_on_the_turn_its_cables_are_on(tmp_path, capsys, emulations,
                                                                   no_leaks):  # noqa: F811
    """Stopped at the second mount's prompt, the roll table rests at -360° (one turn back from home,
    reading 0°); the resumed run's emulators start with the tables where they were left. Reading 0°,
    the table is a turn from home only the journal knows of: taken for home, the run would wind it
    to -720°. The emulators' records of both runs, together, stay within the wrap."""
    station = private_file("az-modbus-tcp", tmp_path)
    answers = tmp_path / "answers.txt"
    answers.write_text("y\nstop\n")
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(station), *EMULATE, "--answers", str(answers),
                       "--out", str(run_dir))
    assert code != 0 and "labcal resume" in err, err
    code, out, err = cli(capsys, "resume", str(run_dir), "--yes", "--no-report", "--json")
    assert code == 0, err
    assert json.loads(out)["points"] == 64
    first, second = emulations
    for table in ("pitch", "roll"):
        left, taken_up = first.rig.axis(table).record[-1][1], second.rig.axis(table).record[0][1]
        assert taken_up == pytest.approx(left, abs=STEP_DEG)  # the tables did not move in between
    assert first.rig.axis("roll").record[-1][1] == pytest.approx(-WRAP, abs=STEP_DEG)  # wound a turn back
    for table in ("pitch", "roll"):
        lows, highs = zip(extremes(first, table), extremes(second, table), strict=True)
        assert -WRAP - STEP_DEG <= min(lows) and max(highs) <= WRAP + STEP_DEG, (table, lows, highs)
