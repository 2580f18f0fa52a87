"""Shared check of the database tests: stored samples recomputed by the DEM."""

import numpy as np

from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.database import probing
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.dem.cell import DemCell


def recheck_against_the_dem(data, meso, rows, threads=None):
    """Recompute samples ``rows`` of database arrays ``data`` for cell ``meso`` and require the
    stored learning state and after-state to be the DEM's own.

    The before-state's normal and unbalanced forces are recomputed from its sizes, free
    positions and springs (exactly, then rounded to the stored dtype); one DEM step of the stored ``d_eps`` from it, from rest
    (``DemCell.at_rest``), gives the
    stored free positions, cell sizes and contacts exactly, and the stored cell moment (dim x
    dim) to rounding (float32). Returns the after-state's arrays of the DEM.
    """
    schema, law, tol = meso.schema(), ContactLaw(), DemSettings().contact_tolerance
    options = {} if threads is None else {"threads": threads}
    context = probing.ProbeContext(DemCell(law, 0.5, **options), meso, schema, {}, law, tol)
    before = evaluate(schema, data["before/cell_size"][rows], data["before/free_position"][rows],
                      data["before/shear_force"][rows], law, tol)
    for name in ("normal_force", "unbalanced"):  # stored in their own dtype (float32: probing.FLOAT32_FEATURES)
        stored = data[f"before/{name}"][rows]
        np.testing.assert_array_equal(before[name].astype(stored.dtype), stored)
    cell = context.cell_model
    new, response = cell.step(cell.at_rest(cell.state_from_arrays(probing.canonical_dem_arrays(
        context, before, data["before/cell_size"][rows]))), data["d_eps"][rows])
    arrays = cell.state_to_arrays(new)
    np.testing.assert_array_equal(free_coordinates(schema, arrays["position"]), data["after/free_position"][rows])
    np.testing.assert_array_equal(arrays["cell_size"], data["after/cell_size"][rows])
    dim = response.moment.shape[-1]
    np.testing.assert_allclose(data["after/moment"][rows].reshape(-1, dim, dim), response.moment, rtol=1e-9,
                               atol=1e-6 * np.abs(response.moment).max())
    np.testing.assert_array_equal(data["after/contact"][rows], arrays["contact"])
    return arrays
