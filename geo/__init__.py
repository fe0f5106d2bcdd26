"""The site frame's link to the mine's grid (:mod:`geo.site_crs`).

A site's frame is the local east-north-up tangent plane at its datum; a site that
declares a projected CRS (an EPSG code) can turn mine-grid coordinates into the site
frame and back, which surveys in and exports out need.
"""
