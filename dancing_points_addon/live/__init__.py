"""Dance live: a dancer's head and hands streamed in, the duet synthesised as
they come, the take kept.

- :mod:`.osc`: OSC packets, read (in place, else with ``python-osc``) and
  written byte for byte as ``python-osc`` writes them;
- :mod:`.protocol`: the two network layouts (the VMC protocol, this project's
  own OSC layout);
- :mod:`.receiver`: the UDP receiver thread, samples and the datagram
  counters; :mod:`.senders`: the sender gate (one dancer, one sender: the
  others counted, not read);
- :mod:`.xr`: Blender's own VR session's poses in motion space (numpy only;
  the Blender side reads ``xr_session_state``);
- :mod:`.session`: the live loop (rows, the start, calibration, causal 30 Hz
  resampling, the synthesizer) and what it leaves (the take and its duet);
  :mod:`.options`: what a session is told and what it leaves;
  :mod:`.stream_meta`: its calibration from the stream's metadata; :mod:`.rows`:
  the take's rows as they come, resampled causally;
- :mod:`.stream`: the sender; :mod:`.cli`: the ``stream`` and ``live`` commands.

Nothing here imports ``bpy``; ``python-osc`` is imported only when a packet
is read or written.
"""

VMC_PORT = 39539  # the VMC protocol's usual receiver (performer) port
OSC_PORT = 39540  # the default of this project's own OSC layout
ROLES = ("leader", "follower")  # whose points a live stream may carry (SPEC §3 role)
