"""Replay: a recording played back onto the bus (:mod:`.replay`, ``zenswarm replay``) and
``verify``, the agents' computation run again on it (:mod:`.verify`, ``zenswarm verify`` and
``replay --verify``); the player's pacing, topic filter and keyboard controls (:mod:`.playback`)."""
