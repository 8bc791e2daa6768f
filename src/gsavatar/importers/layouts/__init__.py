"""Dataset layouts: one reader per file, one signature (:class:`~gsavatar.importers.layouts.common.Layout`:
``name``, ``detect(src)``, ``read(src) -> ImportedSource``). A new layout is a new file and a line in
:data:`LAYOUTS`."""

from gsavatar.importers.layouts.actorshq import ActorsHQ
from gsavatar.importers.layouts.avatarrex import AvatarReX
from gsavatar.importers.layouts.common import ImportedSource, Layout, source_path
from gsavatar.importers.layouts.thuman4 import THuman4

LAYOUTS: dict[str, Layout] = {layout.name: layout for layout in (THuman4(), AvatarReX(), ActorsHQ())}
"""``--layout`` name -> reader (ActorsHQ with its default resolution folder, ``4x``)."""

__all__ = ["ActorsHQ", "AvatarReX", "ImportedSource", "LAYOUTS", "Layout", "THuman4", "source_path"]
