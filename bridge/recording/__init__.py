"""A flight's recording: the MCAP file layout and its reader (:mod:`.mcapio`), the recorder that
writes every sample of the bus into it (:mod:`.recorder`, ``zenswarm record``) and what a
recording holds (:mod:`.info`, ``zenswarm info``)."""
