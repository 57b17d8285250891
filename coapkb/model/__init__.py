"""The knowledge base's data model, below everything that stores, encodes
or sends it: query results (:mod:`.results`) and a replicated module's
writes (:mod:`.deltas`).  Pure records, importing nothing of coapkb outside
this package."""
