"""Flight planning: UFACET-style scan passes scored for polarimetric contrast, and mission export."""
