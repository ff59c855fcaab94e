"""Former home of the rendered-view code, kept for the ``_target_`` s of run configs saved before it was split.

A run's ``.hydra/config.yaml`` names its classes by module path, and ``matl.eval run=<run>``
instantiates them from it, so the names saved by earlier versions must stay importable. New configs
use the modules where the code now lives:

* :class:`~matl.data.view_sampler.ViewSampler` (random cameras): :mod:`matl.data.view_sampler`;
* :class:`~matl.data.queries.RenderedQueries` (``data.queries=rendered``): :mod:`matl.data.queries`;
* :class:`~matl.data.anchors.RenderedRandomAnchors` (``anchors=random_rendered``): :mod:`matl.data.anchors`;
* the cached view pool: :mod:`matl.data.view_pool`; camera projection: :mod:`matl.geometry.camera`;
  render throughput: :mod:`matl.data.render_speed`.

Nothing in matl imports this module.
"""

from matl.data.anchors import RenderedRandomAnchors
from matl.data.queries import RenderedQueries
from matl.data.view_sampler import ViewSampler

__all__ = ["RenderedQueries", "RenderedRandomAnchors", "ViewSampler"]
