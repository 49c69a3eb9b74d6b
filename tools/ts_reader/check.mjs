// Usage: node check.mjs LOG.mcap [MORE.mcap ...]
// Reads each file alone with McapIndexedReader (validating chunk CRCs), as a viewer does with files opened
// together, and prints JSON: per file its topic counts, counts per channel id, metadata names, statistics,
// schema and channel ids;
// and over all files the merged topic counts and metadata names. Exits non-zero on any error.
// Used by tests/test_typescript_reader.py.
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";
import { open } from "node:fs/promises";

const decompressHandlers = await loadDecompressHandlers();

async function readFile(path) {
  const handle = await open(path, "r");
  try {
    const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(handle), decompressHandlers });
    const counts = {};
    const channelCounts = {};
    let last = -1n;
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(message.channelId);
      if (channel === undefined) throw new Error(`a message of channel ${message.channelId}, which the reader does not know`);
      const topic = channel.topic;
      counts[topic] = (counts[topic] ?? 0) + 1;
      channelCounts[message.channelId] = (channelCounts[message.channelId] ?? 0) + 1;
      if (message.logTime < last) throw new Error("messages out of log-time order");
      last = message.logTime;
    }
    const metadata = [];
    for await (const record of reader.readMetadata()) metadata.push(record.name);
    return {
      path, counts, channelCounts, metadata, statistics: Number(reader.statistics?.messageCount ?? -1),
      schemaIds: [...reader.schemasById.keys()], channelIds: [...reader.channelsById.keys()],
    };
  } finally {
    await handle.close();
  }
}

const files = [];
for (const path of process.argv.slice(2)) files.push(await readFile(path));
const counts = {};
for (const file of files) for (const [topic, n] of Object.entries(file.counts)) counts[topic] = (counts[topic] ?? 0) + n;
console.log(JSON.stringify({
  files, counts, metadata: files.flatMap((f) => f.metadata),
  statistics: files.reduce((sum, f) => sum + f.statistics, 0),
}));
