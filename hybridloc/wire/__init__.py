"""The wire contract: key expressions, schemas and limits (:mod:`.protocol`), one symmetric codec per
message (:mod:`.codecs`, the only place that validates what arrives), the records only the wire has
(:mod:`.messages`; the shared ones are in :mod:`hybridloc.types`), Zenoh configuration (:mod:`.zconfig`).
The only place in the library allowed to import ``zenoh``."""
