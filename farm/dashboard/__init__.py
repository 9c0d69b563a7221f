"""The farm dashboard (``farm dashboard``): jobs, shards, failures, workers, renders, trainer
runs, Prometheus metrics and a cancel button, from what the farm and trainer persist.

Modules: :mod:`.jobs` and :mod:`.runs` read the data, :mod:`.pages` draws the HTML,
:mod:`.metrics` the Prometheus collector, :mod:`.app` the routes; :mod:`shaderball.web` is the
guarded web layer under them.
"""
