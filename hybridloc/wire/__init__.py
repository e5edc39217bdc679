"""The wire contract: key expressions and message schemas (:mod:`.protocol`), Zenoh configuration
(:mod:`.zconfig`). The only place in the library allowed to import ``zenoh``."""
