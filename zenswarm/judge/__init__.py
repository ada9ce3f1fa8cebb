"""How a flight is judged, from the vehicles' real states, and when it ends.

- :mod:`zenswarm.judge.verdict`: success, collision, formation and the named cause of a failure.
- :mod:`zenswarm.judge.metrics`: a flight's time series (:class:`~zenswarm.judge.metrics.TimeSeries`)
  and the fields of ``results.json``.
- :mod:`zenswarm.judge.watch`: when a flight ends (:class:`~zenswarm.judge.watch.EndWatch`) and
  which ticks are judged.
- :mod:`zenswarm.judge.results`: ``results.json`` written, the summary line.

Pure (numpy only) but for :mod:`~zenswarm.judge.results`, which writes the files; the simulator
and the supervisor judge, end and write with the same code.
"""
