"""Bottom layer: the typed data model, plugin contracts, errors, column names, resources and the import graph."""
