"""Simulated stays simulated (issue 23): what a dry run's documents say about it, and the Type B
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

import math

from labcal.config.station import CertificateSection, journaled_snapshot
from labcal.config.uncertainty import UncertaintyInputs

NOTICE = ("SIMULATED: these results come from a dry run on labcal's simulated rig or its device emulators, "
          "not from a calibration of a real instrument; they may not be used for measurements and are never "
          "approved")


def simulator_rig(station_text: str) -> dict | None:
    """The simulated rig (its rig-file settings) a run's journaled station snapshot describes: the
    simulated rig of `run --sim`, or the emulators' rig of `run --station … --emulate`; None for a
    station of real devices."""
    doc = journaled_snapshot(station_text)
    if doc is None:
        return None
    if doc.get("kind") == "simulated rig":
        return doc.get("rig") or {}
    if doc.get("kind") == "station" and doc.get("emulate"):
        return ((doc.get("station") or {}).get("emulation") or {}).get("rig") or {}
    return None


def simulator_inputs(rig: dict, samples: int) -> UncertaintyInputs:
    """The Type B inputs the simulated ``rig`` really applies (the module docstring says how each one
    is read), for readings averaged over ``samples`` samples."""
    from labcal.config.emulation import RigConfig

    config = RigConfig.model_validate(rig)  # defaults fill what an older snapshot leaves out
    device, inst = config.device, config.instrument
    arcsec = lambda x: f"{x!r} arcsec"  # noqa: E731 - the station file's own notation
    return UncertaintyInputs.model_validate({
        "pitch_index": arcsec(device.index_arcsec), "roll_index": arcsec(device.index_arcsec),
        "pitch_wobble": arcsec(device.wobble_arcsec), "roll_wobble": arcsec(device.wobble_arcsec),
        "mount_repeatability": arcsec(math.sqrt(3) * device.mount_repeat_arcsec),
        "dmm_noise": f"{inst.noise_v / math.sqrt(max(samples, 1))!r} V",
        "bias_tempco": f"{max(abs(x) for x in inst.tc_bias_v_per_c)!r} V/K",
        "sensitivity_tempco": f"{max(abs(x) for x in inst.tc_scale_per_c)!r} 1/K",
    })


def with_simulator_inputs(section: CertificateSection, station_text: str, settings: dict
                          ) -> CertificateSection:
    """``section`` with the simulator's own Type B inputs where the run was simulated (``settings``:
    the run's sequencer settings, for the samples per reading); unchanged for real devices."""
    rig = simulator_rig(station_text)
    if rig is None:
        return section
    samples = int(((settings or {}).get("settle") or {}).get("samples") or 1)
    return section.model_copy(update={"uncertainty": simulator_inputs(rig, samples)})
