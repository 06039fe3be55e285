"""`--foxglove`: a running pipeline streamed live to the Foxglove app, from the coordinating
process (issue 19 §3). A WebSocket client (what the app is) connects, gets the channels
advertised, subscribes, and receives the run's messages while it runs."""

from __future__ import annotations

import asyncio
import json
import re
import threading
from collections import Counter

import pytest
import websockets

from retriever import Pipeline, Rate, Trigger
from retriever.backends.zenoh.hub import free_port

from ...log.test_foxglove import Cam, Stats

BOUND_S = 30.0  # a bound on any wait, never a speed check
MESSAGE_DATA = 0x01  # the Foxglove WebSocket protocol's binary opcode of a message
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")  # foxglove-sdk's status for a channel it lacks
MAX_RETRIES = 3


@pytest.mark.parametrize("backend", ["zenoh", "dora"])  # (dora: the view is the coordinator's, as on zenoh)
def test_a_websocket_client_gets_the_channels_and_the_messages_of_a_running_pipeline(backend):
    with Pipeline("live") as pipe:
        cam = Cam().configure(name="cam") @ Rate(hz=10)
        stats = Stats().configure(name="stats") @ Trigger("rgb")
        cam.then(stats, map={"rgb": "rgb"})
    port = free_port()
    failure: list[BaseException] = []

    def run() -> None:
        try:  # keep="records": the view still gets the values (it asks for them, as a log does)
            pipe.run(duration=4.0, backend=backend, quiet=True, foxglove=port, keep="records")
        except BaseException as e:  # noqa: BLE001 - reported by the test below
            failure.append(e)

    runner = threading.Thread(target=run)
    runner.start()
    topics: dict[int, str] = {}
    got: dict[str, int] = {}
    retries: Counter = Counter()

    async def subscribe(ws, channel_ids: list[int]) -> None:
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": channel_id, "channelId": channel_id} for channel_id in channel_ids]}))

    async def watch() -> None:
        loop = asyncio.get_running_loop()
        give_up = loop.time() + BOUND_S
        while True:  # the server is up once the run's processes are (a bounded retry, not a wait)
            try:
                ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])
                break
            except OSError:
                assert loop.time() < give_up and not failure, failure
                await asyncio.sleep(0.05)
        async with ws:
            while sum(got.values()) < 12 or "/cam/rgb" not in got:
                message = await asyncio.wait_for(ws.recv(), BOUND_S)
                if isinstance(message, str):
                    body = json.loads(message)
                    if body["op"] == "advertise":
                        for channel in body["channels"]:
                            topics[channel["id"]] = channel["topic"]
                        await subscribe(ws, [channel["id"] for channel in body["channels"]])
                    elif body["op"] == "status" and (unknown := UNKNOWN_CHANNEL.fullmatch(body["message"])):
                        # foxglove-sdk sends an advertise before it records the channel as
                        # advertised to that client (rust/foxglove/src/websocket/connected_client.rs,
                        # advertise_channels, 0.30): a client that subscribes at once may be told
                        # the channel is unknown. The app subscribes when a panel asks; this client
                        # asks again, a bounded number of times.
                        channel_id = int(unknown.group(1))
                        assert channel_id in topics and retries[channel_id] < MAX_RETRIES, body
                        retries[channel_id] += 1
                        await subscribe(ws, [channel_id])
                else:
                    assert message[0] == MESSAGE_DATA
                    subscription = int.from_bytes(message[1:5], "little")
                    got[topics[subscription]] = got.get(topics[subscription], 0) + 1

    try:
        asyncio.run(watch())
    finally:
        runner.join(BOUND_S + 10)
    assert not failure, failure
    assert {"/cam/rgb", "/cam/depth", "/stats/mean", "/retriever/steps/cam"} <= set(topics.values()), topics
    assert got.get("/cam/rgb", 0) >= 1, got
    assert pipe.stats()["cam"].steps == 40
