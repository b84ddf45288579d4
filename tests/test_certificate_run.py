"""What a run journals reaches its certificate: the identities the devices reported (the latest after
a resume), the device model the run's fit used, the ambient conditions entered at the start."""

from __future__ import annotations

import dataclasses
import json

from emulators import TIME_SCALE, cli, no_leaks, private_file  # noqa: F401 - fixture

from labcal.config.station import CertificateSection
from labcal.documents.administration import ItemGiven, administration
from labcal.run.record import load_run
from sim.dmm_emulator import IDN
from sim.smc100_emulator import VERSION


def test_an_emulated_run_certifies_the_identities_the_emulators_reported(tmp_path, capsys, no_leaks):  # noqa: F811
    """`labcal run --emulate` on the SMC100 station: the certificate's equipment gives maker, model,
    serial and firmware as the emulators answer `*IDN?`, `ID?` and `VE` (their own constants, not
    the drivers'); a later `device_identity` event (a resume on a swapped DMM) wins."""
    run_dir = tmp_path / "run"
    code, _, err = cli(capsys, "run", "--station", str(private_file("smc100-serial", tmp_path)), "--emulate",
                       "--time-scale", str(TIME_SCALE), "--yes", "--serial", "SN-7", "--out", str(run_dir))
    assert code == 0, err
    equipment = json.loads((run_dir / "certificate.json").read_text())["administration"]["equipment"]
    pitch, roll, dmm = equipment
    maker, model, serial, firmware = IDN.split(",")
    del dmm["description"]  # the station file's settings, not the subject
    assert dmm == {"role": "DMM", "identity": IDN, "maker": maker, "model": model, "serial": serial,
                   "firmware": firmware}
    for table in (pitch, roll):
        assert table["maker"] == "Newport" and table["firmware"] == VERSION and "serial" not in table
        assert table["model"] == "SMC100 with stage URS100BCC"
    assert f"{maker} {model}, serial {serial}, firmware {firmware}" in (run_dir / "report.html").read_text()

    record = load_run(run_dir)
    swapped = {"dmm": {"model": "Keysight Technologies 34970A", "identity": "swapped", "maker": "Keysight",
                       "serial": "MY99", "firmware": "1-0-0"}}
    resumed = dataclasses.replace(record, events=record.events + (
        {"kind": "device_identity", "data": swapped, "utc": "", "station_time": 0.0, "message": ""},))
    *_, dmm = administration(resumed, CertificateSection(), ItemGiven(), "SN-7").equipment
    assert (dmm.serial, dmm.firmware, dmm.identity) == ("MY99", "1-0-0", "swapped")
