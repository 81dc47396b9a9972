"""The live view of ``capture-run --live --view``: the server (:mod:`pipeline.liveview.server`), the page."""
