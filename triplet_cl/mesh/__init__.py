"""The mesh phase (docs/ARCHITECTURE.md §1, §9): a connected mesh from the triplet soup, its refinement as a
mesh, and the exported PBR assets.

Modules:
    asset     :class:`MeshAsset`, the hand-over between extraction, refinement and export
    extract   soup → connected mesh (TSDF fusion + marching cubes, or vertex welding), cleanup
    transfer  nearest-neighbour attribute transfer soup → mesh vertices
    remesh    gradient-driven Loop subdivision / QEM simplification with attributes carried
    export    GLB (UV atlas + baked PBR textures), OBJ + MTL, PLY, environment map EXR
    bake      UV atlas (xatlas) and texture baking of per-vertex attributes
    envmap    lat-long EXR of the SH environment light (and back)
    refine    the mesh stage: extract → refine as a mesh → export (``triplet extract``)
    metrics   Chamfer distance to a reference mesh
    repair    topology (genus, watertightness) and self-intersection detection / local repair
"""

from .asset import MeshAsset

__all__ = ["MeshAsset"]
