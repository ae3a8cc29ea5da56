"""GridMap geometry: cell indices of world points, including points that are not numbers."""
import warnings

import numpy as np

from terrain_perception.grid import ELEVATION, GridMap


def test_world_to_index_finds_the_cell_and_puts_non_finite_points_outside():
    grid = GridMap.empty(0.05, (1.0, -0.2), (10, 8))
    xy = np.array([[1.0, -0.2], [1.049, -0.151], [1.26, 0.0], [0.99, 0.0],
                   [np.nan, 0.0], [1.2, np.inf], [-np.inf, 0.0], [1e300, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')          # no 'invalid value encountered in cast'
        ij = grid.world_to_index(xy)
    assert ij[:4].tolist() == [[0, 0], [0, 0], [5, 4], [-1, 4]]
    inside = grid.inside(ij)
    assert inside.tolist() == [True, True, True, False, False, False, False, False]
    grid[ELEVATION] = np.full(grid.shape, 0.5)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        z = grid.sample(ELEVATION, xy)
    assert z[:3].tolist() == [0.5, 0.5, 0.5] and np.all(np.isnan(z[3:]))
