"""Surveys in: LAS/LAZ point clouds decimated to a pile's grid and ledgered as ``survey``
events (:mod:`surveys.grid`: the binning and the message, pure; :mod:`surveys.importer`:
reading a file in bounded memory; :mod:`surveys.cli`: ``stockpile survey import``)."""
