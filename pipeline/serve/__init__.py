"""``seqat serve OUT``: a run folder (live or finished) as a local, read-only web map.

* :mod:`pipeline.serve.tiles`: ``mosaic.tif`` as XYZ Web Mercator PNG tiles (rio-tiler,
  morecantile's ``WebMercatorQuad``), re-opened when the file is replaced;
* :mod:`pipeline.serve.runview`: ``status.json``, the cameras and tie points as GeoJSON, read
  from whatever the run folder holds at the time of the request;
* :mod:`pipeline.serve.app`: the Starlette application, the uvicorn server and its socket;
* ``static/``: the page (``index.html``, ``serve.js``, ``serve.css``) and Leaflet 1.9.4,
  vendored (BSD-2-Clause, ``LICENSE-leaflet``): no CDN, the page works offline.
"""
