"""Hardware drivers, one module per device protocol, each behind `labcal.station.RotaryAxis`
or `labcal.station.Voltmeter` (docs/design.md §4)."""
