"""How a flight is judged, from the vehicles' real states.

- :mod:`zenswarm.judge.verdict`: success, collision, formation and the named cause of a failure.
- :mod:`zenswarm.judge.metrics`: a flight's time series (:class:`~zenswarm.judge.metrics.TimeSeries`)
  and the fields of ``results.json``.

Pure (numpy only); the simulator and the supervisor judge with the same code.
"""
