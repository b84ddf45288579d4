"""Every wrong input gets one line: the options that used to end in a traceback or were
accepted silently, each refused in one line naming the option and its valid range, exit 2."""

from __future__ import annotations

import pytest

from labcal.cli import main


def one_line_error(capsys, *args: str) -> str:
    code = main(list(args))
    captured = capsys.readouterr()
    assert code == 2, captured
    assert captured.out == "" and "Traceback" not in captured.err
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    return captured.err


@pytest.mark.parametrize("args,expected", [
    (["run", "--sim", "--replicates", "0"], "argument --replicates: 0 is out of range; expected a whole "
                                            "number x with 1 ≤ x ≤ 100"),
    (["run", "--sim", "--samples", "0"], "argument --samples: 0 is out of range; expected a whole number x "
                                         "with 4 ≤ x ≤ 10000"),
    (["run", "--sim", "--samples", "1"], "argument --samples: 1 is out of range"),
    (["run", "--sim", "--fixed-dwell", "-5"], "argument --fixed-dwell: -5 is out of range; expected a "
                                              "number x with 0 ≤ x ≤ 3600"),
    (["run", "--sim", "--max-dwell", "nan"], "argument --max-dwell: nan is not a finite number"),
    (["run", "--sim", "--seed", "-1"], "argument --seed: -1 is out of range"),
    (["report", "somewhere", "--tolerance-deg", "inf"], "argument --tolerance-deg: inf is not an angle; "
                                                        "expected an angle 0 < x ≤ 180°"),
    (["plan", "generate", "d1", "--n-pitch", "0", "--n-roll", "4", "--pitch-max", "60", "--out", "x.toml"],
     "argument --n-pitch: 0 is out of range; expected a whole number x with 1 ≤ x ≤ 361"),
    (["plan", "generate", "d1", "--n-pitch", "5", "--n-roll", "4", "--pitch-max", "200", "--out", "x.toml"],
     "argument --pitch-max: 200 is out of range; expected a number x with 0 < x ≤ 180"),
    (["plan", "generate", "d1", "--n-pitch", "1", "--n-roll", "2", "--pitch-max", "20", "--out", "x.toml"],
     "the generated plan is not valid: 2 points per replicate cannot determine 4 coefficients"),
    (["plan", "generate", "grid", "--pitch-min", "0", "--pitch-max", "10", "--pitch-step", "1e-9",
      "--roll-min", "0", "--roll-max", "10", "--roll-step", "1", "--out", "x.toml"], "at most 541"),
    (["plan", "generate", "d0", "--pitch=-20,0,400", "--n-roll", "4", "--out", "x.toml"],
     "argument --pitch: '-20,0,400': 400 is out of range"),
    (["fit", "readings.csv", "--level", "1.5"], "argument --level: 1.5 is out of range; expected a number x "
                                                "with 0 < x < 1"),
    (["simulate", "--noise", "-1", "--out", "x.csv"], "argument --noise: -1 is out of range"),
    (["plan", "merit", "four-mount-64", "--pitch-range", "0", "inf"], "argument --pitch-range: inf is not"),
    (["run", "--sim", "--bogus"], "labcal: error: unrecognized arguments: --bogus (usage: labcal --help)"),
])
def test_an_out_of_range_option_is_one_line_naming_it_and_its_range(tmp_path, capsys, monkeypatch, args,
                                                                     expected):
    monkeypatch.chdir(tmp_path)
    assert expected in one_line_error(capsys, *args)
    assert not any(tmp_path.iterdir())  # refused before anything was written


@pytest.mark.parametrize("command,expected", [
    (["run", "--sim", "--yes"], "existing: exists and is not a directory"),
    (["plan", "generate", "tumble"], "existing: exists; choose another --out"),
])
def test_an_existing_file_given_as_out_is_refused_and_kept(tmp_path, capsys, command, expected):
    target = tmp_path / "existing"
    target.write_text("keep me")
    assert expected in one_line_error(capsys, *command, "--out", str(target))
    assert target.read_text() == "keep me"


# --- fit: nonsense refused, gross errors flagged by row, --allow-outliers --------------------
def _readings_csv(tmp_path, capsys, edit=None) -> str:
    """A good readings CSV of four-mount-64 from `labcal simulate` (noise 0.1 mV), optionally edited."""
    import csv

    path = tmp_path / "readings.csv"
    assert main(["simulate", "--noise", "1e-4", "--seed", "3", "--out", str(path)]) == 0
    if edit:
        rows = list(csv.reader(path.read_text().splitlines()))
        edit(rows)
        path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    capsys.readouterr()
    return str(path)


@pytest.mark.parametrize("at,expected", [
    ("10,20,90,0", "the mount Y,U must each be 0 or 180"),
    ("10,nan", "every angle must be a finite number"),
    ("400,0", "pitch and roll must be within -360..360°"),
])
def test_fit_at_refuses_nonsense(tmp_path, capsys, at, expected):
    assert expected in one_line_error(capsys, "fit", _readings_csv(tmp_path, capsys), f"--at={at}")


def test_fit_at_takes_a_negative_pitch_without_equals(tmp_path, capsys):
    assert main(["fit", _readings_csv(tmp_path, capsys), "--at", "-30,100", "--json"]) == 0
    import json

    (prediction,) = json.loads(capsys.readouterr().out)["predictions"]
    assert (prediction["pitch_deg"], prediction["roll_deg"]) == (-30, 100)


def test_fit_refuses_a_reading_no_voltmeter_makes(tmp_path, capsys):
    def huge(rows):
        rows[10][5] = "1e308"
    assert "reading 10: (1e+308," in one_line_error(capsys, "fit", _readings_csv(tmp_path, capsys, huge))


def test_fit_names_a_missed_remount_and_exits_2_unless_allowed(tmp_path, capsys):
    def missed(rows):  # mount 2 (rows 17-32) read while the instrument still sat as mount 1
        for r in range(17, 33):
            rows[r][5:8] = rows[r - 16][5:8]
    path = _readings_csv(tmp_path, capsys, missed)
    code = main(["fit", path, "--json"])
    captured = capsys.readouterr()
    import json

    doc = json.loads(captured.out)  # the result is still printed: nothing lost
    assert code == 2 and {f["row"] for f in doc["gross_errors"]} == set(range(17, 33))
    assert "readings 17–32 (replicate 1) are labelled mount y=180 u=0 but read like mount y=0 u=0" \
        in captured.err and "--allow-outliers" in captured.err.splitlines()[-1]
    assert main(["fit", path, "--allow-outliers"]) == 0
    assert "16 reading(s) flagged; accepted (--allow-outliers)" in capsys.readouterr().err


# --- attitude: readings that are not 1 g are flagged by row ------------------------------------
@pytest.fixture
def fit_json(tmp_path, capsys) -> str:
    assert main(["fit", _readings_csv(tmp_path, capsys), "--json"]) == 0
    path = tmp_path / "fit.json"
    path.write_text(capsys.readouterr().out)
    return str(path)


def test_attitude_flags_dead_saturated_and_impossible_inputs(tmp_path, capsys, fit_json):
    import json

    volts = tmp_path / "v.csv"  # the simulated instrument: B = 0, S = I (1 V/g)
    volts.write_text("vx,vy,vz\n0,0,0\n0.3,0.1,0.9486832980505138\n1e308,0,0\n0.8,0.8,0.8\n")
    code = main(["attitude", "--cert", fit_json, "--csv", str(volts), "--json"])
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert code == 2 and {f["row"] for f in doc["gross_errors"]} == {1, 3, 4}
    assert "reading 1: |(V − B)S⁻¹| = " in captured.err and "reading 3: |(V − B)S⁻¹| = inf g" in captured.err
    assert "closed form and sphere solution differ by" in captured.err  # row 4: |g| = 1.39 g
    assert "Warning" not in captured.err
    good = doc["rows"][1]["closed_form"]
    assert good["pitch_deg"] == pytest.approx(17.457603, abs=1e-3)
    assert main(["attitude", "--cert", fit_json, "--csv", str(volts), "--allow-outliers"]) == 0


def test_closed_form_pitch_uncertainty_is_undefined_at_the_pole_never_huge(tmp_path, capsys, fit_json):
    import csv
    import io

    volts = tmp_path / "v.csv"
    volts.write_text("vx,vy,vz\n1.0001,0,0\n")  # |g| 1.0001: asin clips at 90°, where 1/h was 1e147
    main(["attitude", "--cert", fit_json, "--csv", str(volts), "--allow-outliers"])
    row = next(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    # asin has no usable slope where g_x is clipped: the closed form's linear uncertainty is stated
    # as undefined, the sphere estimator's stays a small number
    assert row["cf_u_pitch_deg"].lower() in ("", "nan", "undefined")
    assert 0 < float(row["ls_u_pitch_deg"]) < 0.1


# --- smaller items ---------------------------------------------------------------------------------
def test_simulate_and_plan_generate_speak_json(tmp_path, capsys):
    import json

    assert main(["simulate", "--out", str(tmp_path / "r.csv"), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["readings"] == 64 and captured.err == ""
    plan = str(tmp_path / "t.toml")
    assert main(["plan", "generate", "tumble", "--four-mounts", "--out", plan, "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["points"] == 24 and captured.err == ""


def test_dry_run_on_a_hardware_station_needs_no_serial(capsys):
    assert main(["run", "--station", "lab-example", "--dry-run", "--json"]) == 0
    import json

    assert json.loads(capsys.readouterr().out)["points"] == 64


def test_report_tables_print_their_text_not_rich_markup():
    import io

    from rich.console import Console

    from labcal.commands.report import rich_table
    from labcal.documents.report_tables import Table

    console = Console(file=io.StringIO(), width=200)
    console.print(rich_table(Table("Statement of conformity", ["verdict"], [["[b]none[/b]"]],
                                   "Give a [certificate] section in the station file.")))
    text = " ".join(console.file.getvalue().split())
    assert "a [certificate] section" in text and "[b]none[/b]" in text
