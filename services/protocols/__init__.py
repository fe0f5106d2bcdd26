"""Wire protocols of the yard's hardware, as pure encoders, decoders and stream parsers.

- :mod:`services.protocols.lms200`: SICK LMS200 binary telegrams (DOMAIN.md §5)
- :mod:`services.protocols.nmea`: NMEA 0183 GGA sentences from GNSS receivers (DOMAIN.md §5)

Nothing here touches a device: the simulator writes the bytes these modules produce to a
pseudo-terminal (:mod:`services.sim.pty`) and consumers feed the bytes they read back in.
"""
