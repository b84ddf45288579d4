"""The simulated rig: CD kinematics with misalignments, the instrument's physics, table motion
and a virtual clock, behind the same interfaces as the hardware drivers."""
