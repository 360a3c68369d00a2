"""The fleet: re-processing campaigns over stored runs on Dask, and what a plant watches.

A campaign (``calstation reprocess``) calibrates every selected stored run again with today's
engine, exactly as ``calstation calibrate --run N`` does (:mod:`calstation.station.reprocess`),
on a Dask cluster, and compares each new H with the one stored:

- :mod:`.selection`: which runs (station, dates, status, limit) and the campaign's key;
- :mod:`.jobs`: what a worker receives and does (no database: recordings from a path or an
  fsspec URL, checked against their sha256);
- :mod:`.compare`: the stored H against the new one, in each parameter, in the work volume, in
  the predicted reconstruction error and in the cube re-measured under the new H;
- :mod:`.tolerance`: what a change is flagged above;
- :mod:`.cluster`: the Dask client (a ``LocalCluster`` or a scheduler's address);
- :mod:`.campaign`: the orchestration: select, skip the rows already stored, send the rest,
  store each result as it arrives;
- :mod:`.view`: a campaign as data, the HTML report and the web station's QA page;
- :mod:`.metrics`: the Prometheus metrics of ``calstation serve``.
"""
