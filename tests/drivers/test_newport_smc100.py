"""The Newport SMC100 driver against its emulator through pyserial: two controllers daisy-chained
on one pty, or behind a raw TCP serial-device server; states, error codes and faults."""

from __future__ import annotations

import pytest
import serial
from emulators import bench_fixtures, emulated, no_leaks, until_still  # noqa: F401 - fixture

from labcal.config.emulation import FaultKind
from labcal.drivers.errors import BadReply, DeviceFault, LinkLost, NoReply, OutOfLimits, Rejected
from labcal.drivers.newport_smc100 import EOL, Smc100Axis
from labcal.drivers.transport import LineTransport, SerialStream
from labcal.sim.faults import Fault

QUICK = {"timeout_s": 0.1, "retries": 2, "reconnect_s": 0.5}


station, smc, smc_slow = bench_fixtures(["smc100-serial", "smc100-tcp"], pitch=QUICK, roll=QUICK)


def test_power_up_state_homing_and_ready(smc):
    emulation, bench = smc
    status = bench.pitch.status()
    assert not status.ready and "NOT REFERENCED from reset (0Ah)" in status.fault
    assert "home it" in status.fault
    assert "URS100BCC" in bench.pitch.identify()
    emulation.rig.axis("pitch").move_to(37.0, "direct")  # where the stage happens to be at power-up
    bench.pitch.prepare()  # homes: 1OR, HOMING until at home, READY from HOMING
    assert bench.pitch.status().words == "READY from HOMING (32h)"
    assert bench.pitch.angle() == 0.0
    settings = emulation.station_config.pitch  # speed and acceleration come from the station file
    assert bench.pitch.ask("VA?") == f"{settings.speed_dps:g}"
    assert bench.pitch.ask("AC?") == f"{settings.accel_dps2:g}"


def test_moves_are_verified_by_read_back(smc_slow):
    emulation, bench = smc_slow
    for axis in bench.axes:
        axis.prepare()
    bench.pitch.move_to(90)
    bench.roll.move_to(270)
    assert bench.pitch.status().words == "MOVING (28h)"
    assert bench.pitch.wait_in_position(60) == pytest.approx(90.0, abs=1e-6)
    assert bench.roll.wait_in_position(60) == pytest.approx(270.0, abs=1e-6)
    assert emulation.rig.axis("roll").travel_deg == pytest.approx(90.0)  # free stage: 0 → 270 is -90°
    assert bench.roll.angle() == pytest.approx(-90.0)


def test_soft_limits_keep_the_stage_within_them(tmp_path, no_leaks):  # noqa: F811
    """A limited stage takes the equivalent angle inside its limits nearest to where it is, and
    moves there directly, never through the forbidden arc; what has no equivalent is refused."""
    limited = {**QUICK, "limits_deg": (-100.0, 200.0)}
    with emulated("smc100-serial", tmp_path, pitch=limited) as (emulation, bench):
        pitch, table = bench.pitch, emulation.rig.axis("pitch")
        pitch.prepare()
        pitch.move_to(270)
        assert pitch.wait_in_position(60) == pytest.approx(270.0)
        assert pitch.angle() == pytest.approx(-90.0)
        pitch.move_to(180)  # 90° backwards would cross -100°: it goes 270° forwards instead
        assert pitch.wait_in_position(60) == pytest.approx(180.0)
        assert table.travel_deg == pytest.approx(90.0 + 270.0)
        seen = emulation.faults["pitch"].requests
        with pytest.raises(OutOfLimits, match="pitch table .*220° is outside the soft limits \\[-100°, 200°"):
            pitch.move_to(220)  # ≡ -140°: no equivalent inside
        assert emulation.faults["pitch"].requests == seen


def test_a_command_the_controller_refuses(smc):
    emulation, bench = smc
    with pytest.raises(Rejected, match="refused PA45.000000: error H \\(not allowed in NOT REFERENCED\\)"):
        bench.pitch.do("PA45.000000")
    bench.pitch.prepare()
    bench.pitch.do("MM0")  # disable
    with pytest.raises(Rejected, match="error J \\(not allowed in DISABLE\\)"):
        bench.pitch.move_to(10)
    assert "DISABLE from READY (3Ch)" in bench.pitch.status().fault
    bench.pitch.prepare()  # enables it again
    assert bench.pitch.status().ready


def test_following_error_disables_the_stage_mid_move(smc_slow):
    emulation, bench = smc_slow
    bench.roll.prepare()
    bench.roll.move_to(180)
    emulation.faults["roll"].add(Fault(FaultKind.ALARM))
    with pytest.raises(DeviceFault, match="DISABLE from MOVING \\(3Dh\\), positioner error: following error"):
        bench.roll.wait_in_position(60)
    assert 0 < abs(bench.roll.angle()) < 180  # stopped where the error struck


def test_silence_after_a_query_is_explained_by_te(smc):
    emulation, bench = smc
    emulation.faults["pitch"].add(Fault(FaultKind.EXCEPTION, code="C", match="TP"))
    with pytest.raises(Rejected, match="refused TP: error C \\(parameter missing or out of range\\)"):
        bench.pitch.angle()


@pytest.mark.parametrize("kind", [FaultKind.NO_REPLY, FaultKind.GARBLED, FaultKind.LATE_REPLY])
def test_lost_garbled_and_late_replies_are_retried(smc, kind):
    emulation, bench = smc
    injector = emulation.faults["pitch"]
    injector.add(Fault(kind, count=2, match="TP", delay_s=0.25))
    assert bench.pitch.angle() == 0.0
    assert injector.count(kind) == 2
    assert bench.pitch.ask("TS")  # the line is clean afterwards: no stale reply answers this


def test_retries_are_bounded(smc):
    emulation, bench = smc
    emulation.faults["pitch"].add(Fault(FaultKind.GARBLED, count=3, match="TP"))
    with pytest.raises(BadReply, match="pitch table .*garbled reply"):
        bench.pitch.angle()


def test_a_lost_acknowledgement_of_a_move_is_not_answered_by_resending_it(smc_slow):
    """The TE after PA is lost while the stage moves at its real speed (20°/s): PA is accepted in
    READY only, so the driver asks the state instead of sending PA again (which error M refuses)."""
    emulation, bench = smc_slow
    bench.pitch.prepare()
    assert bench.config.pitch.speed_dps == 20.0
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))  # the TE after PA is lost
    bench.pitch.move_to(45)
    assert bench.pitch.wait_in_position(60) == pytest.approx(45.0)
    sent = list(emulation.faults["pitch"].recent)
    assert [line for line in sent if line.startswith("1PA")] == ["1PA45.000000"]
    assert emulation.faults["pitch"].count(FaultKind.NO_REPLY) == 1


def test_a_move_that_never_arrived_is_sent_again_from_ready(smc):
    emulation, bench = smc
    bench.pitch.prepare()
    emulation.faults["pitch"].add(Fault(FaultKind.LOST_REQUEST, match="PA"))  # PA lost on the way
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, match="TE"))  # and no TE reply either
    bench.pitch.move_to(30)
    assert bench.pitch.wait_in_position(60) == pytest.approx(30.0)
    assert [line for line in emulation.faults["pitch"].recent if "PA" in line] == ["1PA30.000000"] * 2


def test_the_controller_refuses_pa_while_moving(smc_slow):
    """The emulator, from the manual: PA is allowed in READY only (error M while MOVING)."""
    emulation, bench = smc_slow
    bench.pitch.prepare()
    bench.pitch.move_to(90)
    with pytest.raises(Rejected, match=r"error M \(not allowed in MOVING\)"):
        bench.pitch.do("PA10")
    bench.pitch.stop()


def test_no_stop_is_sent_to_a_stage_that_is_not_referenced(smc):
    emulation, bench = smc
    assert "NOT REFERENCED" in bench.pitch.status().words
    bench.pitch.stop()  # nothing can be moving: the controller would refuse ST (error H)
    assert not [line for line in emulation.faults["pitch"].recent if line.endswith("ST")]
    with pytest.raises(Rejected, match=r"error H \(not allowed in NOT REFERENCED\)"):
        bench.pitch.do("ST")  # what sending it anyway gets


def test_homing_is_not_repeated(smc):
    emulation, bench = smc
    emulation.faults["pitch"].add(Fault(FaultKind.NO_REPLY, count=3, match="TE"))
    with pytest.raises(NoReply, match="pitch table"):
        bench.pitch.prepare()
    assert list(emulation.faults["pitch"].recent).count("1OR") == 1  # homing moves the stage: never resent


def test_port_closed_mid_run_is_reopened(smc):
    emulation, bench = smc
    emulation.faults["roll"].add(Fault(FaultKind.CLOSE_PORT, reopen_s=0.2, match="TP"))
    assert bench.roll.angle() == 0.0


@pytest.mark.timeout(60)  # a link that never gave up would hang here: a failure, not a stuck suite
def test_port_closed_for_good(smc):
    emulation, bench = smc
    emulation.faults["roll"].add(Fault(FaultKind.CLOSE_PORT, match="TP"))
    with pytest.raises((LinkLost, NoReply), match="roll table"):
        bench.roll.angle()
    with pytest.raises(LinkLost, match="kept trying for 0.5 s"):
        bench.pitch.stop()  # the same port: it is gone for both


def test_a_loop_url_echoes_the_command_which_is_no_reply():
    """pyserial's loop:// returns what was sent: the driver must call that garbage, not a position."""
    link = LineTransport("loop://", lambda: SerialStream("loop://", baudrate=57600, bytesize=8, parity="N",
                                                         stopbits=1, xonxoff=False, timeout_s=0.1),
                         eol=EOL, timeout_s=0.1, reconnect_s=0)
    axis = Smc100Axis("roll", link, 1, clock=None, speed_dps=10, accel_dps2=10, retries=0)
    with pytest.raises(BadReply, match="roll table \\(Newport SMC100, address 1 on loop://\\): '' is not a"):
        axis.angle()
    link.close()
    assert isinstance(serial.serial_for_url("loop://"), serial.SerialBase)


def test_stop_after_an_exchange_torn_by_ctrl_c(smc_slow):
    """Ctrl-C between a query and its reply leaves the reply on the line: the stop that follows
    still reaches the controller, and no later answer is the stale one."""
    emulation, bench = smc_slow
    bench.roll.prepare()
    bench.roll.move_to(180)
    read_line = bench.roll.link.read_line
    bench.roll.link.read_line = lambda *a: (_ for _ in ()).throw(KeyboardInterrupt)  # Ctrl-C right after TP
    with pytest.raises(KeyboardInterrupt):
        bench.roll.angle()
    bench.roll.link.read_line = read_line
    bench.roll.stop()
    until_still(bench.roll)  # ST is a decelerating stop: MOVING until the stage is still
    now, table = emulation.rig.clock.now(), emulation.rig.axis("roll")
    assert table.motion_end <= now and 0 < abs(float(table.angle_at(now))) < 179  # stopped mid-move
    assert bench.roll.status().words == "READY from MOVING (33h)"
    assert bench.roll.angle() == pytest.approx(float(table.angle_at(now)), abs=1e-5)
