"""The grid and what is read onto it: CRS helpers, vector and raster layers, LiDAR surfaces, target points."""

from common.exports import lazy_exports

_EXPORTS = {
    "to_pyproj": "crs",
    "transformer": "crs",
    "NODATA_CODE": "grid",
    "Grid": "grid",
    "GridError": "grid",
    "LayerError": "layers",
    "LayerSpec": "layers",
    "LayerWarning": "layers",
    "VectorLayer": "layers",
    "open_source": "layers",
    "read_dem": "layers",
    "read_raster": "layers",
    "read_vector": "layers",
    "LidarError": "lidar",
    "LidarSurface": "lidar",
    "lidar_surface": "lidar",
    "read_point_cloud": "lidar",
    "read_targets": "targets",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
