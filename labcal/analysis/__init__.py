"""The mathematics: kinematics, the one regression core and its models, statistics, design, attitude.

Pure computation on arrays: nothing here reads a file, talks to a device or knows about runs.
"""
