"""Rerun and Foxglove sinks: artrack's messages drawn in a Rerun recording or served to Foxglove, never in a window.

Modules: ``layout`` (entity paths and timelines), ``images`` (frames as Rerun images, the
rate gate), ``scene`` (each message's Rerun rows; pure, no bus), ``blueprint`` (the viewer's
layout), ``recording`` (file and gRPC sinks, logging rows at their time), ``node`` (the live
``viewer`` node kind), ``convert`` (``artrack view IN.mcap OUT.rrd``), ``contents`` (reading
an .rrd back with Rerun's own reader). Foxglove: ``foxglove_messages`` (each message as Foxglove's
well-known messages; pure), ``foxglove_export`` (``artrack export IN.mcap --format foxglove -o OUT.mcap``),
``foxglove_node`` (the live ``foxglove`` node kind, ``artrack view --foxglove``).

Live: ``artrack node viewer --params '{"rrd": "run.rrd"}'`` (add ``"serve": true`` to serve
``rerun+http://127.0.0.1:9876/proxy``), or ``kind = "viewer"`` in a pipeline file.
Offline: ``artrack view IN.mcap OUT.rrd``. Open the file with ``rerun OUT.rrd``.
"""
