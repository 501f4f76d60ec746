"""General file output: atomic writers (:mod:`.atomic`) and text tables (:mod:`.tables`)."""
