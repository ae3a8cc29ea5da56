"""terrain_fill_node: fills the occluded parts of the fine terrain map (paper 000, Fill-Terrain)."""
