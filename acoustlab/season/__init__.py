"""Season-scale localization: long multi-file recordings, detector tables, streaming and sharding."""
