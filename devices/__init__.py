"""Wire protocols of the yard's hardware, as pure encoders, decoders and stream parsers.

- :mod:`devices.lms200`: SICK LMS200 binary telegrams (docs/domain.md §5): the frame
  and its CRC-16, measurement telegrams (ranges <-> 13-bit codes with their error codes),
  the host's mode and status commands, and :class:`~devices.lms200.TelegramReader`, which
  finds whole telegrams in a byte stream
- :mod:`devices.nmea`: NMEA 0183 GGA sentences from GNSS receivers (docs/domain.md §5):
  :func:`~devices.nmea.format_gga`, :func:`~devices.nmea.parse_gga` and
  :class:`~devices.nmea.NmeaReader`, which finds whole sentences in a byte stream

Nothing here touches a device: the simulator writes the bytes these modules produce to a
pseudo-terminal (:mod:`sim.pty`) and the scanner and GNSS services
(:mod:`services.scanner`, :mod:`services.gnss`) feed the bytes they read back in.
"""
