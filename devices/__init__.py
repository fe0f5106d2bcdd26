"""Wire protocols of the yard's hardware, as pure encoders, decoders and stream parsers.

- :mod:`devices.lms200`: SICK LMS200 binary telegrams (DOMAIN.md §5)
- :mod:`devices.nmea`: NMEA 0183 GGA sentences from GNSS receivers (DOMAIN.md §5)

Nothing here touches a device: the simulator writes the bytes these modules produce to a
pseudo-terminal (:mod:`sim.pty`) and consumers feed the bytes they read back in.
"""
