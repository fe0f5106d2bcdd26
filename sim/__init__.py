"""The yard simulator: a ground-truth stockyard that speaks the real hardware protocols.

- :mod:`sim.kinematics`: bucket-wheel reclaimer kinematics and the cutting envelope
- :mod:`sim.world`: the pile on a fine deposition grid (stacking, reclaiming, truth)
- :mod:`sim.sensors`: encoders, GNSS and the LMS200 scanner with their errors
- :mod:`sim.pty`: pseudo-terminals the emulated serial devices write to
"""
