"""MCAP recording, replay and export of the site's events.

- :mod:`replay.mcap_format`: the file conventions (topics, channels, times, chunks)
  and their constants;
- :mod:`replay.mcap_writer`: :class:`~replay.mcap_writer.EventWriter`, events to MCAP;
- :mod:`replay.mcap_records`, :mod:`replay.mcap_scan`: the MCAP record layout and
  :class:`~replay.mcap_scan.McapScan`, a damage-tolerant linear reader;
- :mod:`replay.mcap_entries`: a file's messages as stockpile events
  (:func:`~replay.mcap_entries.read_entries`);
- :mod:`replay.record`, :mod:`replay.record_parts`: the recorder (``stockpile record``,
  ``stockpile service recorder``), live events to MCAP files;
- :mod:`replay.replay`: a file back onto Zenoh or into a ledger (``stockpile replay``);
- :mod:`replay.export`: a ledger's events as an MCAP file (``stockpile export-mcap``);
- :mod:`replay.recover`: salvage a damaged recording (``stockpile record --recover``);
- :mod:`replay.cli`: the ``record``, ``replay`` and ``export-mcap`` commands.
"""
