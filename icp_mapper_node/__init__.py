"""icp_mapper node: dead-reckoning-seeded ICP localisation and the coarse and fine terrain maps."""
