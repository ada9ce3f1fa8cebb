"""A flight's recording: the MCAP file layout and its reader (:mod:`.mcapio`), recovering a
damaged one (:mod:`.recover`, ``zenswarm recover``), the recorder that writes every sample of the
bus into it (:mod:`.recorder`, ``zenswarm record``) through its MCAP sink (:mod:`.sink`) and what
a recording holds (:mod:`.info`, ``zenswarm info``)."""
