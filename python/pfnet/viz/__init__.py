"""Pictures: clouds drawn in the paper's colours (:mod:`~pfnet.viz.rendering`), the
completion galleries (:mod:`~pfnet.viz.gallery`) and the interactive HTML viewer
(:mod:`~pfnet.viz.viewer`)."""
