"""Hardware drivers, one module per device protocol, each behind `labcal.run.station.RotaryAxis`
or `labcal.run.station.Voltmeter` (docs/design.md §4)."""
