"""Robot configuration: topologies (buses, boards in init-chain order, placements, expected
programs) and attribute trees.  Read by the host operations and the virtual fleet alike;
this package imports neither."""
