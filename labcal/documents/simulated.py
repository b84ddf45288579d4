"""Simulated stays simulated: what a dry run's documents say about it, and the Type B
inputs of its budget.

A dry run's readings come from labcal's simulated rig (`labcal run --sim`) or from its device
emulators (`--emulate`), whose physics is a rig file (the journal keeps it). Its certificate, report
and DCC say so first, and its budget lists the error sources that rig really applies, at the sizes it
applies them, instead of zero (the simulated rig has no station file, so the budget used to have no
Type B input at all although the rig errs in index and wobble at every point):

- the tables' index errors and wobble (`labcal.analysis.kinematics.IndexWobble`): each a sum of
  harmonics of its table's angle bounded by the stated amplitude, so the amplitude is the ± half-width
  the station file's ``pitch_index``, ``pitch_wobble``, ``roll_index``, ``roll_wobble`` mean, on the
  same misalignments (pitch index: a; pitch wobble: d, f; roll index: f; roll wobble: e, k);
- the plate's seating at a remount: normal with standard deviation ``mount_repeat_arcsec`` per
  angle, stated as the rectangular half-width with the same variance, √3·σ;
- the instrument's noise: ``noise_v`` per sample, so noise_v/√N for a reading averaged over the
  sequencer's N samples (already in the fit's Type A, shown and not added, as for a bench);
- the instrument's temperature coefficients (the largest of the three sensors'), which the rig
  applies to the lab temperature it simulates;
- no DMM error: the simulated DMM reads the instrument's outputs exactly (0 % of reading and range).

The rig's bias drift (``drift_v_per_h``) has no row of its own in the budget; its effect is in the
residuals, so in the fit's Type A.
"""

from __future__ import annotations

from labcal.config.run_metadata import SequencerRecord
from labcal.config.snapshot import StationSnapshot, simulator_inputs
from labcal.config.station import CertificateSection

NOTICE = ("SIMULATED: these results come from a dry run on labcal's simulated rig or its device emulators, "
          "not from a calibration of a real instrument; they may not be used for measurements and are never "
          "approved")


def with_simulator_inputs(section: CertificateSection, station: StationSnapshot | None,
                          settings: SequencerRecord | None) -> CertificateSection:
    """``section`` with the simulator's own Type B inputs where the run was simulated (``settings``:
    the run's sequencer settings, for the samples per reading); unchanged for real devices."""
    rig = None if station is None else station.simulator_rig()
    if rig is None:
        return section
    samples = 1 if settings is None else settings.settle.samples
    return section.model_copy(update={"uncertainty": simulator_inputs(rig, samples)})
