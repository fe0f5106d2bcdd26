"""The operators' Rerun dashboard: live (``stockpile service dashboard``) and offline.

``stockpile service dashboard --pile ID [--pile ID ...] [--serve] [--rrd PATH]`` follows
the ledger service over Zenoh exactly like the projector service (a catch-up read of
everything committed, then every committed head; :class:`services.projector_service.LiveProjection`
folds it) and logs the pile to Rerun: ``--serve`` hosts a gRPC server on loopback and
the Rerun web viewer for operators' browsers, ``--rrd`` archives the same stream to a
file.  ``stockpile dashboard --ledger PATH --rrd OUT`` renders a finished ledger
offline through the same code (records in global order, as the live service would
have seen them).

Several piles (``--pile`` repeated, both commands; a blending yard's two beds) share one
process, one reading of the ledger and one recording, each pile with its own fold,
tracker and update cadence (:class:`~services.dashboard.piles.PileSet`).  With one pile
the entities are the paths below; with several, every entity of a pile is under
``/piles/<id>`` (``/piles/<id>/site/pile/surface/Fe``, ``/piles/<id>/log``,
``/piles/<id>/cuts/table``, ...; :class:`Config`), ledger-wide lines (gaps, quarantine)
go to every pile's log and the blueprint has a tab per pile.

Timelines come from the data, never the wall clock: ``valid_time`` (timestamp, the
pile's valid time V of the update) and ``ledger_seq`` (sequence, the ledger's global
seq the update includes, so K).  Each update is the pile as of V as known at K, with
``V = max(K, newest valid time read)`` and the update taken at a recorded-time boundary
during catch-up and offline, so it equals ``project(store, pile, V, K)``.

Entities (numbers carry their units in the path):

``/site``                          right-handed, z up (site ENU, metres)
``/site/pile/surface/<analyte>``   Mesh3D of the top surface (one vertex per voxel column),
                                   coloured by the grade of the top voxel (blue low, red
                                   high); one entity per analyte, Fe shown by default
``/site/pile/voxels``              Points3D, one per non-empty voxel, coloured by
                                   ``--analyte``, radius grows with its tonnes (hidden
                                   by default in the blueprint)
``/site/pile/layers``              LineStrips3D, deposit boundaries in cross-sections
                                   (``--layers``), coloured by lot
``/site/machines/<id>``            LineStrips3D: rail, slew tower, boom, wheel, from the
                                   latest ``<id>/wheel`` (or ``<id>/scanner`` through the
                                   declared mount) ``frame_transform`` and the kinematics
``/site/scan``                     Points3D, the latest scan georeferenced
``/site/cuts``                     LineStrips3D, each reclaim cut's footprint at its floor
``/site/plan``                     LineStrips3D, offline with ``--plan-machine``: the next
                                   bench's planned cuts, footprints at their floor coloured by
                                   predicted grade (``/plan/table``: the same as a table)
``/series/pile/tonnes_t/{known_then,known_now}``, ``/series/pile/grade_pct/<A>/...``,
``/series/pile/assayed_fraction/...``, ``/series/pile/volume_m3``: Scalars
``/series/cuts/tonnes_t/{geometry,belt_scale}``, ``/series/cuts/grade_pct/<A>/{at_end,
known_now}``, ``/series/cuts/assayed_fraction/{at_end,known_now}``: one point per cut at
its end time
``..._hi``, ``..._lo`` beside ``/series/pile/tonnes_t/known_then``, ``/series/pile/
grade_pct/<A>/known_then``, ``/series/cuts/tonnes_t/geometry`` and ``/series/cuts/
grade_pct/<A>/at_end``: the figure +/- one standard deviation (its band, pale blue;
``tonnes_sd`` and ``grade_sd`` of :func:`projector.query.summarise`)
``/log``                           TextLog: lots, passes, cuts, assay arrivals (lateness),
                                   superseded assays, reconciliation deltas above
                                   ``--delta-threshold-pp``, gaps, quarantined input
``/cuts/table``, ``/status``, ``/legend``: TextDocuments (markdown), latest only

"As known then" is logged once per update.  "As known now" is re-evaluated from a
compact inventory of each history point (volume per lot and deposition second) with the
assays known at the newest K: offline it is logged once, at the end, as known at the
ledger's head; live it is logged with each update and re-logged for past points when a
late assay revises them (the newest row at a valid time is the current figure).
Only the latest state of each 3D entity is sent, and only when it changed.

The package's interface (the service registry in ``stockpile.service_cli`` and the
``stockpile`` command use it):

- :func:`add_arguments`, :func:`config_from_args`, :class:`Config`: the service's options
- :func:`main` ``(config, *, stopper=None)``: the live service
- :func:`register`: the ``stockpile dashboard`` command; :func:`render_ledger` (one pile),
  :func:`render_piles` (several) and :class:`RenderResult`: the offline renderer it runs
- :class:`Dashboard`: records in, Rerun out; :class:`PileSet`: several piles' dashboards
  on one recording; :func:`blueprint`: the default layout

Modules: ``config`` (options), ``tracker`` (what the records said), ``history`` (the
pile over time), ``cuts`` (reclaim cuts and the planned bench), ``scene`` (the 3D pile,
machines, scan, status), ``pose`` (the reclaimer geometry drawn), ``style`` (colours,
blueprint, series styles), ``recorder`` (logging at the data's time and the piles'
prefixes), ``core`` (the :class:`Dashboard`), ``piles`` (:class:`PileSet`), ``viewer``
(recording sinks and the web viewer), ``offline`` and ``live`` (the two commands).
"""

from __future__ import annotations

from services.dashboard.config import Config, add_arguments, config_from_args
from services.dashboard.core import Dashboard
from services.dashboard.live import main
from services.dashboard.offline import RenderResult, register, render_ledger, render_piles
from services.dashboard.piles import PileSet
from services.dashboard.style import blueprint

__all__ = ["Config", "add_arguments", "config_from_args", "main", "render_ledger",
           "render_piles", "register", "Dashboard", "PileSet", "RenderResult", "blueprint"]
