"""Step 1's inputs: a mesh or point cloud loaded into one :class:`~fastmesh.shapes.io.Shape` (``io``, with the
point files of ``pointfiles``, the checks before parsing of ``precheck``, the format sniffing of ``sniff``),
sampled and normalised; the frame it is generated in (``canonical``) and a flat-faced input rebuilt from its
planes (``planar``)."""
