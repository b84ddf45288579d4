"""The mount check that a miswired station cannot pass: at its attitude, the tables exchanged (their
SMC100 addresses swapped), a table turning the wrong way, or the DMM's channels in another order
each read far from what the plan expects, and the check names which. The expected readings are
computed here, from the nominal gravity of Soto §5 by hand, not by labcal.run.mounting."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from cli import cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.analysis.kinematics import Mount
from labcal.config.emulation import default_instrument
from labcal.run.mounting import CHECK_ATTITUDE, identify

TRUTH = default_instrument()  # the simulated and emulated instrument: ~5 V/g, 20 µV noise per sample
SAMPLES = 10  # a check window averages the settle settings' samples
SIGMA = TRUTH.noise_v / math.sqrt(SAMPLES)  # one check reading's noise, per channel
# each mount reverses two of gravity's components (y = 180°: x and y; u = 180°: y and z)
SIGNS = {(0, 0): (1, 1, 1), (180, 0): (-1, -1, 1), (0, 180): (1, -1, -1), (180, 180): (-1, 1, -1)}


def gravity(pitch_deg: float, roll_deg: float, mount: tuple[int, int]) -> np.ndarray:
    """g = [sin p, cos p sin r, cos p cos r] on the first mount (Soto §5), the mount's reversals."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    g = np.array([math.sin(p), math.cos(p) * math.sin(r), math.cos(p) * math.cos(r)])
    return g * np.array(SIGNS[mount])


def volts(g: np.ndarray) -> np.ndarray:
    return np.asarray(TRUTH.B) + g @ np.asarray(TRUTH.S)


def alternatives(pitch: float, roll: float, mount: tuple[int, int]) -> dict[str, np.ndarray]:
    """What the DMM reads when the plan commands (pitch, roll) on ``mount`` and the station is
    wired otherwise than its file says, one fault at a time."""
    found = {"tables exchanged": volts(gravity(roll, pitch, mount)),
             "pitch reversed": volts(gravity(-pitch, roll, mount)),
             "roll reversed": volts(gravity(pitch, -roll, mount))}
    right = volts(gravity(pitch, roll, mount))
    for order in itertools.permutations(range(3)):
        if order != (0, 1, 2):
            found[f"channels {''.join('xyz'[c] for c in order)}"] = right[list(order)]
    return found


@pytest.mark.parametrize("mount", list(SIGNS))
def test_every_miswiring_moves_the_check_reading_by_far_more_than_the_noise(mount):
    """At the check attitude each alternative is ≥ 20 σ from the expected reading on every channel
    pair (here: > 10 000 σ, a third of a g and more); at the old (30°, 30°) the exchanged tables
    read exactly as expected — a check there proved nothing."""
    right = volts(gravity(*CHECK_ATTITUDE, mount))
    separation = {name: float(np.linalg.norm(v - right)) / SIGMA
                  for name, v in alternatives(*CHECK_ATTITUDE, mount).items()}
    assert min(separation.values()) >= 20, separation
    assert min(separation.values()) > 1e4  # what the attitude was chosen for: 0.38 g × 5 V/g ≫ 6 µV
    old = alternatives(30.0, 30.0, mount)["tables exchanged"]
    assert np.linalg.norm(old - volts(gravity(30.0, 30.0, mount))) / SIGMA < 1e-6


FAULT_WORDS = {"tables exchanged": "the tables look exchanged: pitch moves what the plan calls roll",
               "pitch reversed": "the pitch table turns the wrong way",
               "roll reversed": "the roll table turns the wrong way"}


@pytest.mark.parametrize("mount", list(SIGNS))
def test_the_check_names_each_miswiring_in_one_phrase_and_passes_the_right_one(mount):
    """Each alternative's reading, with noise, is named for what it is, on the stated mount; the
    station as its file says reads as the stated mount with no fault."""
    rng = np.random.default_rng(sum(mount))
    stated = Mount(*mount)
    seen, wiring = identify(volts(gravity(*CHECK_ATTITUDE, mount)) + rng.normal(0, SIGMA, 3), None, stated)
    assert (seen, wiring.faults) == (stated, [])
    for name, reading in alternatives(*CHECK_ATTITUDE, mount).items():
        seen, wiring = identify(reading + rng.normal(0, SIGMA, 3), None, stated)
        assert len(wiring.faults) == 1, (name, wiring.faults)
        if name.startswith("channels"):
            read = ", ".join(name.split()[1])
            assert wiring.faults[0].endswith(f"its x, y, z channels read the instrument's {read}"), name
        else:
            assert wiring.faults[0].startswith(FAULT_WORDS[name]), (name, wiring.faults)
        assert seen == stated, name


def test_a_wrong_mount_still_reads_as_that_mount_with_no_wiring_fault():
    """The check's first use: the instrument on another mount than asked is that mount, not a fault."""
    for actual, stated in itertools.permutations(SIGNS, 2):
        seen, wiring = identify(volts(gravity(*CHECK_ATTITUDE, actual)), None, Mount(*stated))
        assert (seen, wiring.faults) == (Mount(*actual), []), (actual, stated)


def test_swapped_smc100_addresses_are_named_at_the_first_mount_check_before_any_reading(tmp_path, capsys,
                                                                                      no_leaks):  # noqa: F811
    """`labcal run --station --emulate` on SMC100 emulators whose controller at the pitch address
    drives the roll table (and the reverse): both answer alike, so only gravity tells. The run names
    the exchange in one line at its first mount check, keeps no reading and sends no point."""
    from labcal.config.station import load_station

    station = private_file("smc100-tcp", tmp_path, "tables_exchanged = true\n")  # its last table: [emulation]
    assert load_station(station)[0].emulation.tables_exchanged
    answers = tmp_path / "answers.txt"
    answers.write_text("y\na\n")  # mounted; then, at the pause the check makes, abort
    code, _, err = cli(capsys, "run", "--station", str(station), "--emulate", "--time-scale", str(TIME_SCALE),
                       "--no-report", "--answers", str(answers), "--plan", "one-mount-16",
                       "--out", str(tmp_path / "run"), "--db", str(tmp_path / "j.db"))
    assert code == 1  # stopped by the operator at the pause: resumable once the station file is mended
    assert "Fault: the mount check on y=0°, u=0° (pitch 33°, roll 76°): the tables look exchanged: pitch " \
           "moves what the plan calls roll (check the tables' addresses or cables)" in err, err
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["points_recorded"] == 0 and run["status"] == "stopped"
    from labcal.store.journal import Journal

    with Journal(tmp_path / "j.db") as journal:
        events = journal.events(1)
    kinds = [e.kind for e in events]
    fault = kinds.index("fault")
    assert "the tables look exchanged" in events[fault].message
    # from the mount to the notice: one move (to the check attitude) and its one window, no point
    moves = [e for e in events[:fault] if e.kind == "move"]
    assert (moves[-1].data["pitch"][1], moves[-1].data["roll"][1]) == CHECK_ATTITUDE
    assert kinds[kinds.index("answer"):fault].count("move") == 1 and "point" not in kinds
