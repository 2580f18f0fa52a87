"""The meso-DEM backend: ``warp_hcell.dem.cell.DemCell`` (batched few-grain DEM cells in Warp kernels)."""

from warp_hcell.dem.cell import DemCell, DemCellState

__all__ = ["DemCell", "DemCellState"]
