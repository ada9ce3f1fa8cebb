"""Views of a flight: the neutral scene (:mod:`.scene`: obstacles, UAVs, metrics) and its two
encoders, Foxglove (:mod:`.foxglove_scene`, :mod:`.foxglove`) and Rerun (:mod:`.rerun_scene`); the
live view (:mod:`.live`, ``--live``) and the export of a recording to a file (:mod:`.export`,
``zenswarm export``)."""
