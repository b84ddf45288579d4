"""The run machinery: the sequencer and what it needs to move, settle, measure and ask.

The sequencer and the run around it (`labcal.run.sequencer`, `labcal.run.runner`), its typed events
and their bus (`labcal.run.events`, the journal subscribed first by `labcal.run.journaling`), the
prompts and Ctrl-C (`labcal.run.operator`, `labcal.run.interrupts`), the mount check
(`labcal.run.mounting`), the readings' checks (`labcal.run.checks`), the timing models (motion,
settling and its pool, the order of the points, the duration estimate) and the notifier, one more
subscriber. What it keeps is `labcal.store`'s; the devices it drives are `labcal.devices`'.
"""
