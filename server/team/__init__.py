"""Team services on the shared map (issue 26): frontier goals (:mod:`.frontiers`), their SSI auction
(:mod:`.auction`), ORCA collision advisories (:mod:`.orca`), follow-the-leader references
(:mod:`.follow`); :mod:`.service` computes them for the REST routes at a bounded rate."""
