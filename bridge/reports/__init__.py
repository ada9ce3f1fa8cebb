"""Reports: a flight's figures and results from its recording (:mod:`.report`, ``zenswarm
report``: the flight loaded from the recording, :mod:`.flight`; its figures, :mod:`.figures`) and
a campaign's report from its results table (:mod:`.sweep_report`, ``zenswarm sweep report``: the
campaign loaded from its directory, :mod:`.campaign`; its statistics per parameter cell,
:mod:`.sweep_stats`; its plots, :mod:`.sweep_figures`)."""
