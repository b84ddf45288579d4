"""Model settling's pool kept across runs: which runs share it, what it carries, and what it saves."""

from __future__ import annotations

import hashlib
import json
import math
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from cli import in_process

from labcal.cli import main
from labcal.config.settings import SettleSettings
from labcal.run.settle import POOL_MIN, TailPool
from labcal.run.settle_pool import load, pool_key, save
from labcal.sim.clock import VirtualClock
from labcal.sim.tail_sensor import TailSensor
from labcal.store import labdb
from labcal.store.journal import RunRow

MODEL = SettleSettings(tau_s=0.5, noise_v=20e-6, samples=10, mode="model")
STEP_V = np.array([0.5, -0.25, 0.1])


def row(station: dict | str, serial: str | None = None, run: str = "run-1", identity=None) -> RunRow:
    return RunRow(1, "d", "p", "", "", station if isinstance(station, str) else json.dumps(station), "",
                  "0", {}, {"device_identity": identity} if identity else {}, "", None, "complete", None,
                  serial, None, run)


def sim(seed: int, tau: float = 0.5, speed: float = 20.0) -> dict:
    return {"kind": "simulated rig", "seed": seed,
            "rig": {"seed": 0, "speed_dps": speed, "instrument": {"tau_s": tau, "noise_v": 2e-5}}}


def test_a_simulated_instrument_is_its_truth_not_its_seed_and_a_station_its_devices_not_their_links():
    same = pool_key(row(sim(1)), MODEL), pool_key(row(sim(2)), MODEL)
    assert same[0].key == same[1].key and same[0].noise != same[1].noise
    assert pool_key(row(sim(1, tau=0.6)), MODEL).key != same[0].key  # another simulated instrument
    assert pool_key(row(sim(1, speed=10.0)), MODEL).key != same[0].key  # another (simulated) station
    assert pool_key(row(sim(1), serial="ACC-1"), MODEL).key != same[0].key
    assert pool_key(row(sim(1)), MODEL.model_copy(update={"tau_s": 0.6})).key != same[0].key  # sums' grid
    assert pool_key(row(sim(1)), MODEL.model_copy(update={"pool": "none"})) is None

    bench = {"kind": "station", "emulate": False, "station": {
        "pitch": {"driver": "oriental-az", "unit": 1, "port": "/dev/ttyUSB0", "timeout_s": 0.5},
        "roll": {"driver": "oriental-az", "unit": 2, "port": "/dev/ttyUSB0"},
        "dmm": {"driver": "keysight-34970a", "nplc": 10, "tcp": "10.0.0.5:5025"}}}
    moved = json.loads(json.dumps(bench))
    moved["station"]["pitch"].update(port="/dev/ttyUSB1", timeout_s=1.0)
    moved["station"]["roll"]["port"] = "/dev/ttyUSB1"
    key = pool_key(row(bench, "ACC-7"), MODEL).key
    assert pool_key(row(moved, "ACC-7"), MODEL).key == key  # a USB adapter on another port
    slower = json.loads(json.dumps(bench))
    slower["station"]["dmm"]["nplc"] = 1
    assert pool_key(row(slower, "ACC-7"), MODEL).key != key
    other_dmm = {"dmm": {"model": "Keysight 34970A", "identity": "KEYSIGHT,34970A,MY1,1.0"}}  # as journaled
    assert pool_key(row(bench, "ACC-7", identity=other_dmm), MODEL).key != key
    # the identities as journaled, the same documents (the pool of every earlier run keeps its key)
    identified = pool_key(row(bench, "ACC-7", identity=other_dmm), MODEL)
    assert identified.identity["station"]["identities"] == other_dmm
    assert identified.key == hashlib.sha256(json.dumps(identified.identity, sort_keys=True,
                                                       separators=(",", ":")).encode()).hexdigest()
    assert pool_key(row(bench, "ACC-8"), MODEL).key != key
    by_type = MODEL.model_copy(update={"pool": "type", "instrument_type": "QA-700"})
    assert pool_key(row(bench, "ACC-7"), by_type).key == pool_key(row(bench, "ACC-8"), by_type).key


def test_type_pooling_needs_the_type():
    with pytest.raises(ValueError, match="instrument_type"):
        SettleSettings(pool="type")


def records(n: int, seed: int, poles=((1.0, 0.5),)):
    """``n`` step records of a `TailSensor` (in position 1 s after the motion ended, 0.2 s samples)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        clock = VirtualClock(1.0)
        sensor = TailSensor(clock, rng.normal(0.0, 1.0, 3), STEP_V * rng.uniform(0.2, 1.0), poles, 0.2,
                            MODEL.noise_v, rng)
        out.append((sensor.read(25).volts, 1.1 + 0.2 * np.arange(25)))
    return out


def test_a_pool_kept_in_the_lab_database_goes_on_as_one_pool_would(tmp_path):
    """Two runs' records pooled through the database give the pool one run fed all of them would
    (the reference), and the second run's key holds both runs as sources."""
    first, second = records(30, 1), records(30, 2)
    reference = TailPool(MODEL.tau_s, MODEL.noise_v)
    for volts, t in first + second:
        reference.add(volts, t)
    key = pool_key(row(sim(1)), MODEL)
    with labdb.connect(tmp_path / "lab.sqlite") as db:
        state, note, keep = load(db, key)
        assert state is None and keep and "no earlier runs" in note
        pool = TailPool(MODEL.tau_s, MODEL.noise_v, state)
        for volts, t in first:
            pool.add(volts, t)
        save(db, key, pool)
        later = pool_key(row(sim(2), run="run-2"), MODEL)
        state, note, keep = load(db, later)
        assert keep and state is not None and state.records == 30 and "30 step records of 1" in note
        pool = TailPool(MODEL.tau_s, MODEL.noise_v, state)
        for volts, t in second:
            pool.add(volts, t)
        assert pool.records == 60 and pool.own_records == 30
        assert pool.tau() == pytest.approx(reference.tau(), rel=1e-9)
        assert pool.slow_z() == pytest.approx(reference.slow_z(), rel=1e-9, abs=1e-9)
        save(db, later, pool)
        sources = json.loads(db.execute("SELECT sources FROM settle_pools").fetchone()[0])
        assert [s["run"] for s in sources] == ["run-1", "run-2"]


def test_a_dry_run_repeating_a_seed_does_not_count_its_noise_twice(tmp_path):
    key = pool_key(row(sim(1)), MODEL)
    with labdb.connect(tmp_path / "lab.sqlite") as db:
        pool = TailPool(MODEL.tau_s, MODEL.noise_v)
        for volts, t in records(20, 1):
            pool.add(volts, t)
        save(db, key, pool)
        again = pool_key(row(sim(1), run="run-2"), MODEL)
        state, note, keep = load(db, again)
        assert state is None and not keep and "repeats it" in note
        resumed = load(db, key)  # the same run, resumed: goes on with what it kept
        assert resumed[0] is not None and resumed[0].records == 20 and resumed[2]


@pytest.mark.parametrize("poles, before, why", [
    (((1.0, 0.65),), 300, "model: "),  # τ 30 % longer than its history's: the pooled records bend
    # τ 10 % longer after a long history, which dilutes the pooled score: the two-sample test
    (((1.0, 0.55),), 1000, "model: this run's τ differs from the earlier runs'"),
    (((0.99, 0.5), (0.01, 1.5)), 300, "model: "),  # a 1 % second pole appeared
])
def test_an_instrument_that_changed_under_its_key_stops_the_pool_vouching(poles, before, why):
    """Records of a one-pole sensor (τ = 0.5 s), then 30 records of the changed sensor: the pool
    (the pooled slow-tail score, or this run's records against the history's) sees a mismatch,
    and vouches no more."""
    history = TailPool(MODEL.tau_s, MODEL.noise_v)
    for volts, t in records(before, 3):
        history.add(volts, t)
    assert not history.mismatch
    pool = TailPool(MODEL.tau_s, MODEL.noise_v, history.state())
    for volts, t in records(POOL_MIN + 20, 4, poles):
        pool.add(volts, t)
    assert pool.mismatch.startswith(why)


def test_the_same_instrument_is_not_taken_for_a_changed_one():
    """Twenty runs of 20 records after a 300-record history of the same sensor: the two-sample
    tests are at Z_DETECT = 4 (p ≈ 6e-5 each), so none of the twenty may cry wolf."""
    history = TailPool(MODEL.tau_s, MODEL.noise_v)
    for volts, t in records(300, 5):
        history.add(volts, t)
    for run in range(20):
        pool = TailPool(MODEL.tau_s, MODEL.noise_v, history.state())
        for volts, t in records(20, 100 + run):
            pool.add(volts, t)
        assert pool.mismatch == ""


def run_sim(tmp_path, capsys, seed: int, mode: str, db: str, rig: str | None = None) -> tuple[dict, list]:
    args = ["run", "--sim", "--yes", "--json", "--no-report", "--seed", str(seed), "--settle", mode,
            "--db", str(tmp_path / db), "--out", str(tmp_path / f"{db}-{mode}-{seed}")]
    assert main(args + (["--rig", rig] if rig else [])) == 0
    summary = json.loads(capsys.readouterr().out)
    with sqlite3.connect(tmp_path / db) as con:
        rows = con.execute("SELECT settle_s, settle_verdict FROM points WHERE run_id = "
                           "(SELECT max(id) FROM runs) ORDER BY seq").fetchall()
        events = [m for (m,) in con.execute("SELECT message FROM events WHERE kind='settle_pool' AND "
                                            "run_id = (SELECT max(id) FROM runs)")]
    return summary, [rows, events]


HISTORY = 4  # model runs of four-mount-64, seeds 1…4, before the runs the tests compare


@pytest.fixture(scope="module")
def history(tmp_path_factory) -> Path:
    """A lab database holding the pool of HISTORY model runs of one simulated instrument (seeds 1…4):
    made once for the module (four whole runs), each test goes on from a copy of its own."""
    folder = tmp_path_factory.mktemp("history")
    with pytest.MonkeyPatch.context() as env:  # as the autouse lab_database fixture does for a test
        for name in ("XDG_RUNTIME_DIR", "XDG_CONFIG_HOME", "XDG_CONFIG_DIRS"):
            env.setenv(name, str(folder / name.lower()))
        for name in ("LABCAL_CONFIG", "LABCAL_NOTIFY", "LABCAL_STATION", "LABCAL_JOURNAL"):
            env.delenv(name, raising=False)
        for seed in range(1, HISTORY + 1):
            code, _, err = in_process("run", "--sim", "--yes", "--json", "--no-report", "--seed", str(seed),
                                      "--settle", "model", "--db", str(folder / "pool.sqlite"), "--out",
                                      str(folder / f"model-{seed}"))
            assert code == 0, err
    return folder / "pool.sqlite"


def pool_copy(history: Path, tmp_path: Path) -> None:
    """The module's history as this test's pool.sqlite (SQLite's backup: the WAL's pages included)."""
    copy = tmp_path / "pool.sqlite"
    with closing(sqlite3.connect(history)) as source, closing(sqlite3.connect(copy)) as target:
        source.backup(target)


def history_then_pair(tmp_path, capsys, history: Path, seed: int):
    """The module's history of HISTORY model runs, then the pair: seed by model settling (pooled) and
    conventionally."""
    pool_copy(history, tmp_path)
    model = run_sim(tmp_path, capsys, seed, "model", "pool.sqlite")
    conventional = run_sim(tmp_path, capsys, seed, "detect", f"conv-{seed}.sqlite")
    return model, conventional


def settle_sum(result) -> float:
    return sum(s for s, _ in result[1][0])


def test_a_pooled_history_lets_four_mount_64_settle_by_the_model(tmp_path, capsys, history):
    """Four model runs of one simulated instrument (seeds 1–4), then a fifth: it starts with the
    288 records of the four (the journal says so: 4 × (64 points, 4 mount checks, 4 returns to
    them)), the pool vouches from its start, so its summed settle time is well below a conventional
    run of the same seed (measured 0.80× at 272 records; 0.9 leaves room for the seeds' noise), and
    its coefficients lie within 3 SE of that run's. A run of another simulated instrument (τ 0.6 s)
    starts with no records."""
    model, conventional = history_then_pair(tmp_path, capsys, history, HISTORY + 1)
    assert "starts with 288 step records of 4 earlier run(s)" in model[1][1][0]
    settled = [v for _, v in model[1][0] if v.startswith("settled (model")]
    assert len(settled) >= 30
    assert settle_sum(model) <= 0.9 * settle_sum(conventional)
    fitted, reference = (np.array(r[0]["fit"]["coefficients"]) for r in (model, conventional))
    se = np.array(conventional[0]["fit"]["standard_errors"])
    assert np.max(np.abs(fitted - reference) / se) < 3
    rig = tmp_path / "other.toml"
    rig.write_text("[instrument]\ntau_s = 0.6\n")
    other = run_sim(tmp_path, capsys, 9, "model", "pool.sqlite", str(rig))
    assert "no earlier runs of this instrument" in other[1][1][0]


def paired_bias(tmp_path, capsys, history: Path, pairs: int) -> tuple[float, float]:
    """Mean and Monte Carlo SE over ``pairs`` paired runs (the module's history of four model runs,
    then each pair: one seed by pooled model settling and conventionally) of the coefficients' paired
    difference in the conventional run's SE, on the coefficient where the mean is largest."""
    pool_copy(history, tmp_path)
    diffs = []
    for k in range(pairs):
        seed = 100 + k
        model = run_sim(tmp_path, capsys, seed, "model", "pool.sqlite")
        conventional = run_sim(tmp_path, capsys, seed, "detect", f"conv-{seed}.sqlite")
        fitted, reference = (np.array(r[0]["fit"]["coefficients"]) for r in (model, conventional))
        diffs.append(((fitted - reference) / np.array(conventional[0]["fit"]["standard_errors"])).ravel())
    d = np.array(diffs)
    worst = int(np.argmax(np.abs(d.mean(axis=0))))
    return float(d[:, worst].mean()), float(d[:, worst].std(ddof=1) / math.sqrt(pairs))


def test_paired_runs_show_no_bias_of_pooled_model_settling(tmp_path, capsys, history):
    """Three pairs: the mean paired difference, less three of its Monte Carlo SE, is within 0.1 SE
    of the coefficient (the pool grows between pairs: 272 records and more)."""
    mean, mc_se = paired_bias(tmp_path, capsys, history, 3)
    assert abs(mean) - 3 * mc_se <= 0.1 and mc_se < 0.1


@pytest.mark.slow
def test_paired_runs_show_no_bias_of_pooled_model_settling_many(tmp_path, capsys, history):
    mean, mc_se = paired_bias(tmp_path, capsys, history, 20)
    assert abs(mean) - 3 * mc_se <= 0.1 and mc_se < 0.05


def test_a_short_history_is_pooled_but_not_compared():
    """Five records of history (fewer than POOL_MIN: no τ̂ of their own) then a run of the same
    sensor: pooled, no mismatch claimed from a comparison the history cannot support."""
    history = TailPool(MODEL.tau_s, MODEL.noise_v)
    for volts, t in records(5, 7):
        history.add(volts, t)
    pool = TailPool(MODEL.tau_s, MODEL.noise_v, history.state())
    for volts, t in records(40, 8):
        pool.add(volts, t)
    assert pool.records == 45 and pool.mismatch == ""
