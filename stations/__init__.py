"""Example station files (data), shipped with labcal and found by name (`labcal station list`)."""
