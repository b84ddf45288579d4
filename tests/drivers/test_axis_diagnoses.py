"""What the tables' drivers say when something goes wrong, through
the real drivers on the emulators: a lost stop acknowledgement is not a stall; "the tables are
still" only once their status says so (a stop decelerates: AZ STOP input and SMC100 ``ST``,
hardware_protocols.md §2.1 "Stop (decelerate)" and §2.2 "Stop"); the SMC100 homing timeout says
what happened and what to check; the SMC100's software limits (``SL``/``SR``, §2.2 "Limits") are
read before anything moves and a station that reaches beyond them is refused."""

from __future__ import annotations

import threading
import time

import pytest
from conftest import quiet_console
from emulators import MOTION_SCALE, emulated, no_leaks  # noqa: F401 - fixture

from labcal.bench.setup import known_settle, prepare
from labcal.config.emulation import FaultKind
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.devices.station import StopFailed
from labcal.drivers.errors import DeviceFault
from labcal.drivers.oriental_az import INPUT_REF, Input
from labcal.run.operator import OperatorDeclined, ScriptedOperator
from labcal.run.runner import calibrate
from labcal.sim.az_emulator import AzServer
from labcal.sim.faults import Fault
from labcal.store.journal import Journal

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}
STOP_BIT = 1 << 5  # the STOP input, bit 5 of the reference input command (hardware_protocols.md §2.1)


def az_unit(emulation, table: str):
    for _, _, server in emulation.servers.values():
        if isinstance(server, AzServer):
            for unit in server.drives.units.values():
                if unit.name == table:
                    return server.drives, unit
    raise AssertionError(f"no AZ drive for {table}")


@pytest.mark.parametrize("station", ["az-modbus-tcp", "az-modbus-rtu"])
def test_a_lost_stop_acknowledgement_is_not_a_stall(station, tmp_path, no_leaks):  # noqa: F811
    """Every reply to the pitch drive's STOP write is lost (the drive obeyed): the stop is reported
    as not confirmed, and the STOP input stays on. Before, the next move started nothing and was
    diagnosed as "in position ... from the target; check for a stall or a slipping coupling"; now
    the driver releases the input first (read back off) and the move arrives."""
    with emulated(station, tmp_path, MOTION_SCALE, pitch=QUICK, roll=QUICK) as (emulation, bench):
        drives, unit = az_unit(emulation, "pitch")
        bench.pitch.move_to(180)
        emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="fc06 007D", count=3))
        with pytest.raises(StopFailed) as failed:
            bench.station().stop()
        assert failed.value.tables == ("pitch",) and "no reply" in str(failed.value)
        assert unit.inputs & STOP_BIT  # the drive took the stop; only its acknowledgements were lost
        assert [table for table, _ in drives.stops][:1] == ["pitch"]
        bench.pitch.move_to(90)
        assert bench.pitch.wait_in_position(60) == pytest.approx(90.0)
        assert not unit.inputs & STOP_BIT


def test_a_move_the_drive_will_not_start_is_named_not_called_a_stall(tmp_path, no_leaks):  # noqa: F811
    """A STOP input left on by something labcal does not know of (another program, a stop whose
    release was lost before this process began): the move starts nothing. Before: "check for a
    stall or a slipping coupling"; now the message says the move did not start and why."""
    with emulated("az-modbus-tcp", tmp_path, pitch=QUICK, roll=QUICK) as (emulation, bench):
        bench.pitch.link.write_one(bench.pitch.unit, INPUT_REF + 1, Input.STOP)
        bench.pitch.move_to(90)
        with pytest.raises(DeviceFault) as fault:
            bench.pitch.wait_in_position(60)
        message = str(fault.value)
        assert "the move to 90° did not start" in message and "its STOP input is on" in message
        assert "--reset-alarms" in message and "stall" not in message and "\n" not in message


class WatchingOperator(ScriptedOperator):
    """Answers from a file; at the pause prompt, notes which emulated tables are still at that moment."""

    def __init__(self, console, path, emulation):
        super().__init__(console, path)
        self.emulation = emulation
        self.still_at_prompt: list[dict[str, bool]] = []

    def after_pause(self, why, moving=()):
        rig, now = self.emulation.rig, self.emulation.rig.clock.now()
        self.still_at_prompt.append({name: rig.axis(name).motion_end <= now for name in ("pitch", "roll")})
        return super().after_pause(why, moving)


@pytest.mark.parametrize("station", ["az-modbus-tcp", "smc100-serial"])
def test_the_pause_says_the_tables_are_still_only_once_they_are(station, tmp_path, no_leaks):  # noqa: F811
    """A fault on the pitch table (mid-way of its 90°) while the roll table swings 180° at full
    speed (20°/s; the plan's first move, from the load position to (90°, 180°)): the run
    stops both and pauses. A stop decelerates (0.5 s from 20°/s at 40°/s² on AZ, 0.25 s at 80°/s²
    on SMC100, in the rig's time, here wall time); before, the prompt said "The tables are still"
    while the roll table was still braking; now it comes once every table's status says it is not
    moving (the emulator's own motion is the reference)."""
    plan_file = tmp_path / "swing.toml"
    plan_file.write_text('name = "swing"\nreplicates = 1\nmounts = [[0, 0]]\n'
                         'points = [[90, 180], [0, 0], [0, 90], [45, 270]]\n')  # in this order
    plan, text = load_plan(str(plan_file))
    (tmp_path / "answers.txt").write_text("y\na\n")
    with emulated(station, tmp_path, 1.0) as (emulation, bench):
        rig = emulation.rig
        hooks = emulation.hooks()
        station_ = bench.station(**hooks)
        prepare(bench, station_, say=lambda text: None)

        def fault_mid_swing() -> None:  # pitch faults while both move, roll at full speed
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                now, pitch, roll = rig.clock.now(), rig.axis("pitch"), rig.axis("roll")
                speed = abs(float(roll.angle_at(now + 1e-3) - roll.angle_at(now))) / 1e-3
                if speed > 19.9 and pitch.motion_end - now > 1.0 and roll.motion_end - now > 1.0:
                    with rig.lock:
                        if station.startswith("az"):
                            drives, unit = az_unit(emulation, "pitch")
                            drives.raise_alarm(unit, 0x10)
                        else:
                            server = next(s for _, _, s in emulation.servers.values()
                                          if getattr(s.device, "positioners", None))
                            server.device.alarm("pitch", 0x0020)
                    return
                time.sleep(0.005)

        watcher = threading.Thread(target=fault_mid_swing)
        watcher.start()
        operator = WatchingOperator(quiet_console(), tmp_path / "answers.txt", emulation)
        settings = SequencerSettings(settle=known_settle(rig.rig.instrument), check_mount=False, order="plan")
        (tmp_path / "run").mkdir()
        try:
            with Journal(tmp_path / "j.sqlite") as journal, pytest.raises(OperatorDeclined):
                calibrate(plan, text, station_, "test", operator, settings, tmp_path / "run", journal)
        finally:
            watcher.join()
    assert operator.still_at_prompt == [{"pitch": True, "roll": True}]


def test_the_smc100_homing_timeout_says_what_happened_and_what_to_check(tmp_path, no_leaks):  # noqa: F811
    """Homing from 90° at 20°/s takes 4.5 s (plus acceleration); with home_timeout_s = 0.5 the
    driver stops the stage and says so: before, "homing took longer than 0.5 s" and nothing else.
    The controller goes NOT REFERENCED from HOMING (0Bh, manual §2.2 state table) on ST."""
    slow_homing = {**QUICK, "home_timeout_s": 0.5}
    with emulated("smc100-serial", tmp_path, 10.0, pitch=slow_homing) as (emulation, bench):
        table = emulation.rig.axis("pitch")
        table.move_to(90.0, "direct")  # where the stage happens to be at power-up
        emulation.rig.clock.advance_to(table.motion_end)
        with pytest.raises(DeviceFault) as fault:
            bench.pitch.prepare()
        message = str(fault.value)
        assert "homing (OR) did not find home within home_timeout_s = 0.5 s" in message
        assert "NOT REFERENCED from HOMING (0Bh)" in message and "home switch" in message
        assert "raise home_timeout_s in the station file" in message and "\n" not in message
        emulation.rig.clock.advance_to(table.motion_end)
        assert 0.0 < float(table.angle_at(emulation.rig.clock.now())) < 90.0  # stopped on its way home


@pytest.mark.parametrize(("table", "controller", "refused"), [
    ("pitch", (-50.0, 200.0), "the station's limits_deg [-100°, 280°] exceed the controller's software "
                              "limits [-50°, 200°] (SL, SR)"),
    ("roll", (-170.0, 170.0), "the controller's software limits are [-170°, 170°] (SL, SR) but the station "
                              "file gives no limits_deg"),
])
def test_smc100_software_limits_narrower_than_the_station_are_refused_before_anything_moves(
        table, controller, refused, tmp_path, no_leaks):  # noqa: F811
    """smc100-serial's pitch has limits_deg [-100, 280] and its roll none. A controller whose SL/SR
    are narrower would refuse a planned angle mid-run (error G); now `prepare` reads SL? and SR?
    first and refuses in one line, before homing (nothing moves)."""
    with emulated("smc100-serial", tmp_path, pitch=QUICK, roll=QUICK) as (emulation, bench):
        server = next(s for _, _, s in emulation.servers.values() if getattr(s.device, "positioners", None))
        positioner = next(p for p in server.device.positioners.values() if p.name == table)
        positioner.limits = controller
        axis = getattr(bench, table)
        with pytest.raises(DeviceFault) as fault:
            axis.prepare()
        assert refused in str(fault.value) and "\n" not in str(fault.value)
        assert not any(line.endswith("OR") for line in emulation.faults[table].recent)  # never homed
        assert emulation.rig.axis(table).travel_deg == 0.0
        positioner.limits = (-1e9, 1e9) if table == "roll" else (-100.0, 280.0)  # as the station says
        axis.prepare()  # accepted
