"""Hardware drivers, one module per device protocol, each behind `labcal.devices.station.RotaryAxis`
or `labcal.devices.station.Voltmeter` (docs/design.md §4)."""
