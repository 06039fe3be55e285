// Read an MCAP file with Foxglove's TypeScript reader (@mcap/core's McapIndexedReader, what the
// Foxglove app uses): summary, chunk indexes, message indexes. Prints JSON: the statistics' count,
// the messages read per topic, and their log times in the order the reader gave them; the file's
// profile and the encodings of its schemas and channels.
// Usage: node mcap_indexed_read.mjs FILE (with @mcap/core and fzstd installed beside NODE_PATH).
import { open } from "node:fs/promises";
import { createRequire } from "node:module";

const require = createRequire(process.env.MCAP_JS_MODULES + "/");
const { McapIndexedReader } = require("@mcap/core");
const fzstd = require("fzstd");

const handle = await open(process.argv[2], "r");
const readable = {
  size: async () => BigInt((await handle.stat()).size),
  read: async (offset, length) => {
    const buffer = new Uint8Array(Number(length));
    await handle.read(buffer, 0, Number(length), Number(offset));
    return buffer;
  },
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: { zstd: (data, size) => fzstd.decompress(data, new Uint8Array(Number(size))) },
});
const topics = {};
const times = [];
for await (const message of reader.readMessages()) {
  const topic = reader.channelsById.get(message.channelId).topic;
  topics[topic] = (topics[topic] ?? 0) + 1;
  times.push(Number(message.logTime));
}
await handle.close();
const encodings = (items, key) => [...new Set([...items.values()].map((item) => item[key]))].sort();
console.log(JSON.stringify({
  statistics: Number(reader.statistics?.messageCount ?? -1), topics, times, profile: reader.header.profile,
  schemaEncodings: encodings(reader.schemasById, "encoding"),
  messageEncodings: encodings(reader.channelsById, "messageEncoding"),
}));
