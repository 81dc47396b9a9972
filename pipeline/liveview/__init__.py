"""The live view of ``capture-run --live --view``: the server (:mod:`roomcap.pipeline.liveview.server`), the
page."""
