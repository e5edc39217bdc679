"""Radio maps, passive survey labelling, fingerprint positioning and similarity."""
