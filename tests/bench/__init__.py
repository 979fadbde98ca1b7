"""Two-process benchmark of artrack's typed messages over Zenoh (``make bench``).

The bench process publishes; a sink process it spawns (``tests.bench.sink``) subscribes and
decodes. They talk peer to peer over a loopback TCP endpoint on a free port, multicast
scouting off, no router (``services.bus.session.session_config``); Zenoh's default config
applies otherwise, so large payloads travel through its implicit shared memory.

Measured, each figure a median over ``RUNS`` runs:

* images (640x480 mono8, 1280x720 bgr8), ``typed`` (``protocol.Image`` encoded per message,
  decoded by the sink to a numpy view) against ``raw`` (the same pixels as plain bytes of the
  same payload size, read with ``np.frombuffer``): zero-loss throughput and one-way latency,
  with typed and raw runs alternated so machine noise does not tilt their ratio;
* poses (``protocol.Pose``, JSON codec) with the RESULT role's QoS: the same two figures.

Output: one JSON line per figure on stdout, then one line describing the machine.
Files here are not named ``test_*``: pytest does not collect them.
"""
