"""Calibration plan files (data). Found by name through `labcal.config.plans.shipped_plans`."""
