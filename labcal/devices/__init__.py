"""The devices' interfaces: what a rotary table and a voltmeter are to labcal.

The small protocols the drivers (`labcal.drivers`) and the simulated rig (`labcal.sim`) implement
and the sequencer drives (`labcal.devices.station`: a rotary axis, a voltmeter, the station that
bundles them, the clock and the critical section), and cable wrap, the limit a table's cables set
on which way round a move may go (`labcal.devices.winding`). A driver imports these and
`labcal.errors`, nothing else of labcal (an import contract says so), as ophyd-async's and
Bluesky's protocols keep device code apart from the plans that use it.
"""
