"""Maps: load, validate and save map GeoJSON (FORMATS.md section 3); map building.

The public surface is :func:`load_map`, :func:`map_from_geojson`, :func:`save_map`,
:func:`build_map` and the frozen :class:`Map` with its :class:`Reflector` list and
spatial queries (:meth:`Map.query_sector`, :meth:`Map.query_bounds`).
"""

from sonarloc.maps.geojson import (
    Map,
    MapFeature,
    Reflector,
    build_map,
    load_map,
    map_from_geojson,
    map_to_geojson,
    save_map,
    sector_polygon,
)

__all__ = ["Map", "MapFeature", "Reflector", "build_map", "load_map", "map_from_geojson",
           "map_to_geojson", "save_map", "sector_polygon"]
