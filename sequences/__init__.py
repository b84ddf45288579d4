"""Calibration plan files (data). Found by name through `labcal.plan.shipped_plans`."""
