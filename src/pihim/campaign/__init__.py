"""Campaigns at field scale: flight logs, frame matching, a results store, distributed runs and reports.

* :mod:`pihim.campaign.logs` -- vehicle and gimbal poses from PX4 ULog,
  ArduPilot DataFlash ``.bin`` and plain ``frames.csv`` logs; frames matched
  to a log by time (position interpolated, attitude by slerp, gimbal
  composed); frames outside the log reported, never guessed.
* :mod:`pihim.campaign.store` -- the embedded SQLite results store
  (campaign, flight, frame, heliostat, per-facet results with provenance),
  versioned and migrated, with CSV and Parquet export.
* :mod:`pihim.campaign.flight` -- a flight directory (``flight.json``,
  ``frames.csv``, an optional autopilot log, raw frames) and the synthetic
  flight of a plan (``pihim simulate-flight``).
* :mod:`pihim.campaign.selection` -- per frame, the HUA-target pairs in view
  whose contrast criteria hold (the rest skipped with a counted reason).
* :mod:`pihim.campaign.run` -- the campaign run on dask.distributed:
  resumable and idempotent.
* :mod:`pihim.campaign.report` -- the static HTML field-health report.

Heavy dependencies (pyulog, pymavlink, dask, pyarrow) are imported where used.
"""

from __future__ import annotations
