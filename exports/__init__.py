"""Files for mine planning and GIS, written from a pile as of (V, K), in the mine grid.

- :mod:`exports.placement`: the site's CRS from the ledger, and where a pile's grid lies
  in the mine grid (a raster's affine transform fitted to the exact conversion);
- :mod:`exports.geotiff`: the ground, each deposit's top and the top surface as the bands
  of one GeoTIFF (rasterio);
- :mod:`exports.dxf`: the top surface as a polyface mesh and its contours (ezdxf);
- :mod:`exports.blocks`: the voxel block model as CSV or Parquet;
- :mod:`exports.cuts`: each cut's footprint and grade as GeoJSON;
- :mod:`exports.cli`: ``stockpile export surfaces|mesh|blocks|cuts``.

Every writer raises ValueError for what it cannot write (a pile not declared, a site
without a CRS) and writes its file whole or not at all (a temporary name, then a rename).
"""
