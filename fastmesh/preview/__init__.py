"""Images and overlays of meshes: the numpy z-buffer rasteriser (``render``), its PNG encoder (``png``) and the
input points drawn beside a result (``overlay``), which the service's preview serves."""
