"""The result as written: the files (``output``'s :class:`~fastmesh.export.output.MeshOut`, encoded by
``meshfiles``), triangles paired into quads (``quads``), a UV layout (``layout``), the input's texture baked onto
it (``bake``) and the placement asked for (``placement``)."""
