"""Recording the bus to MCAP, playing recordings back, and reading them offline.

Modules: ``writing`` (payloads -> MCAP files, filed by ``protocol.codec.peek``, split into
parts), ``reading`` (a sequential, damage-tolerant MCAP reader and ``recover``),
``byte_queue`` (the recorder's bounded FIFO), ``playback`` (replay timing, pause and step),
``info`` and ``export`` (offline tools), ``trajectories``, ``pairing`` and ``scoring`` (``artrack
eval``). ``record_node`` and ``replay_node``
are the two bus-side nodes; only they import the runtime and Zenoh.

Recording format (MCAP 1.x, chunked, zstd by default)
-----------------------------------------------------
* One channel per (key, message type): topic = the Zenoh key exactly as it travelled
  (``ar/rig0/cam0/image``). Each message is the payload's bytes exactly as they travelled,
  never decoded and re-encoded.
* Messages of a type this build knows get its JSON Schema (``protocol.schemas.json_schema``,
  schema encoding ``jsonschema``, schema name = the message's schema name, ``artrack.Pose``):

  - JSON-layout messages: message encoding ``json``; stock MCAP readers decode them.
  - frame-layout messages (with arrays): message encoding ``application/vnd.artrack.frame``
    (``protocol.codec.MEDIA_FRAME``); the schema describes the frame's JSON header, see
    ``protocol.codec`` for the layout of the bytes around it.

  Channel metadata: ``artrack.layout`` (``json`` or ``frame``) and ``artrack.version``.
* Payloads that are not artrack messages of a known schema and version, or whose JSON part,
  header or array extents are damaged (``protocol.codec.peek`` fails), are recorded too, raw:
  schema id 0, message encoding ``application/octet-stream``, channel metadata
  ``artrack.layout = raw`` and ``artrack.reason`` (why the first one was not recognised).
  The recorder counts them as decode errors and reports them, and replay publishes them
  back, so downstream nodes see exactly the inputs they saw live.
* ``log_time`` = arrival time at the recorder (``time.time_ns()``); ``publish_time`` = the
  message's source stamp ``header.stamp_ns`` (the arrival time for raw payloads);
  ``sequence`` = the message's index on its channel in the session (from 0, continuing
  across split parts, modulo 2**32).
* Messages are stored in arrival order; replay plays them in file order.
* Metadata records: ``artrack.recording`` at the start of each file (``namespace``, ``rig``,
  ``keys`` as a JSON list, ``part``, ``started_ns``) and ``artrack.recorder`` when the file is
  finished (``messages`` in the file, ``received``, ``dropped`` and ``unrecognised`` so far in
  the session). A file without the second one was not finished (the recorder was killed).
* Split recordings (``--split-size``/``--split-duration``) are written as ``OUT_000.mcap``,
  ``OUT_001.mcap``, ... next to ``OUT.mcap`` (stem, underscore, part number of at least three
  digits, suffix); each part is a complete MCAP file with its own schemas and channels. A
  size split closes a part once its size on disk plus the payloads not yet compressed reaches
  the limit; a duration split starts a new part with the first message whose log time is the
  duration or more after the part's first. A recording never overwrites ``OUT`` or its parts.
* A recorder restarted by its supervisor after it was killed goes on in ``OUT.part2.mcap``,
  ``OUT.part3.mcap``, ... (split as above when asked), each naming ``OUT`` under
  ``continues`` in its ``artrack.recording`` record; the killed part is left as it was.

Exit codes of ``artrack replay``, ``info`` and ``export``: 0 done, 1 unexpected failure, 2 bad
arguments or unusable file (not MCAP, no such key) or bus error, 3 the file is damaged
(truncated or corrupt): everything before the damage was used and one line says where (byte
offset, intact messages, time into the recording) and why it stopped. ``artrack record``: 0
after a clean stop, 2 bad arguments (an existing output, overlapping key expressions) or bus
error. ``artrack control``: 0 answered, 1 no such node answered, 2 refused command or bus error.
"""
