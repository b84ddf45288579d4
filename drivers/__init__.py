"""Hardware drivers, one module per device protocol, each behind `labcal.station.RotaryAxis`
or `labcal.station.Voltmeter` (DESIGN.md §4)."""
