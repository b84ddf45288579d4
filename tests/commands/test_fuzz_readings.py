"""Seeded fuzz of the readings parser, `labcal fit` and `labcal attitude --csv`: on any
fuzzed readings file each exits 0 or 2 — never a traceback, never a stray warning — and the parser
accepts the file or refuses it in one line. `fuzz_readings` says how the files are made; a
failure names the seed that rebuilds its file. The ordinary suite runs a sample and the seeds
that once failed; the slow suite runs 2 100 files, as the issue's count did."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from fuzz_readings import fit_options, fuzzed_readings
from hostile_files import one_line_or_accepted

from labcal.cli import main
from labcal.config.readings_csv import read_readings

# seeds whose files once ended in a traceback: S singular (identical or zero volts: 2, 30, 233), a
# base regressor that is zero on every row (one attitude, g_x = 0: 235, 1425)
ONCE_FAILED = (2, 30, 233, 235, 1425)
SAMPLE = 40  # the ordinary suite: a few seconds


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[str, Path]:
    """A simulated four-mount-64 readings file (0.1 mV noise) and its fit, to fuzz and to convert with."""
    folder = tmp_path_factory.mktemp("fuzz")
    readings, fit = folder / "readings.csv", folder / "fit.json"
    assert main(["simulate", "--noise", "1e-4", "--seed", "3", "--out", str(readings)]) == 0
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["fit", str(readings), "--json", "--model", "linear"]) == 0
    fit.write_text(out.getvalue())
    return readings.read_text(), fit


def check_seeds(seeds, base, tmp_path, capsys) -> dict[tuple[str, int], int]:
    """Each seed's file through the parser, fit and attitude; returns how often each exit code came."""
    text, fit = base
    path = tmp_path / "fuzzed.csv"
    counts: dict[tuple[str, int], int] = {}
    for seed in seeds:
        path.write_text(fuzzed_readings(text, seed), encoding="utf-8")
        one_line_or_accepted(read_readings, path)
        for command in (["fit", str(path), "--json", *fit_options(seed)],
                        ["attitude", "--cert", str(fit), "--csv", str(path)]):
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # a RuntimeWarning on stderr is noise to a technician
                try:
                    code = main(command)
                except BaseException as exc:
                    pytest.fail(f"seed {seed}: labcal {' '.join(command[:1] + command[2:])} raised "
                                f"{type(exc).__name__}: {exc}")
            err = capsys.readouterr().err
            assert code in (0, 2), f"seed {seed}: {command[0]} exit {code}: {err}"
            assert "Traceback" not in err
            if code == 2:
                assert err.strip(), f"seed {seed}: {command[0]} exit 2 without saying why"
            counts[command[0], code] = counts.get((command[0], code), 0) + 1
    return counts


def test_the_seeds_that_once_failed(base, tmp_path, capsys):
    counts = check_seeds(ONCE_FAILED, base, tmp_path, capsys)
    assert counts.get(("fit", 2)) == len(ONCE_FAILED)  # each refused, in one line


def test_a_sample_of_fuzzed_files(base, tmp_path, capsys):
    counts = check_seeds(range(10_000, 10_000 + SAMPLE), base, tmp_path, capsys)
    # the fuzz must reach the fits, not only the parser's refusals: some files are fitted
    assert counts.get(("fit", 0), 0) >= 1 and counts.get(("attitude", 0), 0) >= 1, counts


CHUNKS = 6  # the 2 100 seeds in six tests, so that the slow step spreads them over every core


@pytest.mark.slow
@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_two_thousand_fuzzed_files(chunk, base, tmp_path, capsys):
    counts = check_seeds(range(chunk, 2_100, CHUNKS), base, tmp_path, capsys)
    least = 100 // CHUNKS  # the fuzz must reach the fits in every chunk, not only the parser's refusals
    assert counts.get(("fit", 0), 0) >= least and counts.get(("attitude", 0), 0) >= least, counts
