"""Step 1's inputs: the :class:`~fastmesh.shapes.shape.Shape` type with its normalisation, formats and errors
(``shape``); a mesh or point cloud loaded, sampled and exported (``io``, with the point files of ``pointfiles``,
the checks before parsing of ``precheck``, the format sniffing of ``sniff`` and a glTF's texture of
``texture``); the frame it is generated in (``canonical``) and a flat-faced input rebuilt from its planes
(``planar``)."""
