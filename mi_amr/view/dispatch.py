"""A page's message to the engine, one way for both transports: the
websocket server (`server`) and the notebook widget (`widget`).

Each transport parses a message (`protocol.parse` for the websocket's text,
`protocol.parse_message` for the widget's decoded JSON), takes an ``ack``
itself (its frame gate), applies a view change at once where it arrived
(`VIEW_CHANGES`: a drag's changes never wait behind a snapshot or a field
switch) and hands the other messages to `answer`, on a worker thread where
they may block. Whatever goes wrong becomes one line for the page
(`error_reply`), never the end of the session.
"""

from __future__ import annotations

from . import protocol as p

#: The page messages that change a view (`ViewEngine.change`): quick, applied where they arrive.
VIEW_CHANGES = (p.CameraChange, p.TFChange, p.DenoiseChange, p.ModeChange, p.HybridChange, p.IsoChange)


def answer(engine, view, msg, out_dir, budget=None) -> p.ServerMessage | None:
    """The engine's reply to ``msg``, a page message of ``view`` other than
    ``ack``: a view change applied (the new histogram when its range or
    units changed, else None), the histogram, a snapshot written into
    ``out_dir`` within ``budget`` (`protocol.SnapshotDone`), the TF
    editor's, annotations', clip's and slice's (`ViewEngine.request`).
    Blocking for a snapshot and a field switch (a worker thread's call). A
    `ValueError` or `OSError` says what is wrong; the view is then unchanged."""
    match msg:
        case p.IsoChange():                      # refused: the view's isosurfaces as they stay, for the page
            try:
                engine.change(view, msg)
            except ValueError as e:
                return p.Error(str(e), msg.TYPE, iso=engine.iso_state(view))
            return None
        case p.CameraChange() | p.TFChange() | p.DenoiseChange() | p.ModeChange() | p.HybridChange():
            return engine.histogram(view) if engine.change(view, msg) else None     # a new range or units
        case p.HistogramRequest():
            return engine.histogram(view)
        case p.SnapshotRequest(name=name):
            shot = engine.take_snapshot(view, out_dir, name, budget)
            return p.SnapshotDone(tuple(str(f) for f in shot.files), shot.spp, notes=tuple(shot.notes) or None)
        case p.TFSave() | p.TFLoad() | p.FieldChange() | p.Describe() | p.ClipChange() | p.AnnotateChange() \
                | p.AnnotationsRequest() | p.SliceRequest():     # the TF editor's, annotations, clip, slice
            return engine.request(view, msg)
    raise ValueError(f"not a message for the engine: {msg.TYPE}")


def error_reply(e: Exception, about: str | None) -> p.Error:
    """``e`` as the page's one-line error about the message type ``about``
    (None: not known yet): a `ProtocolError` as it is worded (about what it
    names), a `ValueError` or `OSError` as its message, anything else (a bug:
    the session goes on) with its type named."""
    if isinstance(e, p.ProtocolError):
        return p.Error(str(e), e.about)
    if isinstance(e, (ValueError, OSError)):
        return p.Error(str(e), about)
    return p.Error(f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}", about)
