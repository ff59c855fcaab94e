"""The user's textured meshes as canonical sources: ``ycb``, ``apc``, ``arc``, ``meshes`` (``docs/datasets.md``).

See :mod:`.sources` for the folder layouts, :mod:`.io` for loading (textures resolved relative to
their ``.mtl``), :mod:`.frames` for object frames and planes from the oriented bounding box, and
:mod:`.manifest` for the per-dataset shape types.
"""

from matl.data.meshes.io import MeshError, load_mesh_parts
from matl.data.meshes.manifest import Manifest, ManifestEntry, ManifestError
from matl.data.meshes.sources import APCSource, ARCSource, MeshFolderSource, MeshSource, YCBSource

__all__ = [
    "APCSource",
    "ARCSource",
    "Manifest",
    "ManifestEntry",
    "ManifestError",
    "MeshError",
    "MeshFolderSource",
    "MeshSource",
    "YCBSource",
    "load_mesh_parts",
]
