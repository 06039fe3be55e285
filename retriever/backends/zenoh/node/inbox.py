"""What a node loop's inbox holds: ``(kind, key, message)``, one item per message received.

The kinds say which handler takes an item (``NodeLoop.handle``): a data message of the input
stream ``key`` (producer, port), a progress message of the producer ``key`` (or ``None``: a
progress query timed out), both as their bytes; a control message of the run, opened and
decoded (a protocol record, or the WireError that refused it); or a nudge (after work a
receiving thread did in the main thread's stead: look again at the time to wake). A producer in
the same process (group.py) hands its events over as they are (``EVENTS``: a list of
wire.DataMessage, values by reference), with nothing to decode or check. A transport whose
receiving thread died hands over the exception (``FAILED``): the loop raises it, and the run
fails saying why, rather than the node never hearing, nor stepping, again.
"""

DATA, PROGRESS, CONTROL, NUDGE, EVENTS, FAILED = 0, 1, 2, 3, 4, 5

#: put in the inbox after work done on a receiving thread: the main thread looks again
NUDGED = (NUDGE, None, None)
