"""Replay: a recording played back onto the bus and ``verify``, the agents' computation run again
on it (:mod:`.replay`, ``zenswarm replay`` and ``zenswarm verify``); the player's pacing, topic
filter and keyboard controls (:mod:`.playback`)."""
