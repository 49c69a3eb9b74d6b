// Usage: node check.mjs LOG.mcap
// Prints JSON {topic: message count} read with McapIndexedReader (validating chunk CRCs),
// exits non-zero on any error. Used by tests/test_typescript_reader.py.
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";
import { open } from "node:fs/promises";

const path = process.argv[2];
const handle = await open(path, "r");
try {
  const decompressHandlers = await loadDecompressHandlers();
  const reader = await McapIndexedReader.Initialize({
    readable: new FileHandleReadable(handle),
    decompressHandlers,
  });
  const counts = {};
  let last = -1n;
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    const topic = reader.channelsById.get(message.channelId).topic;
    counts[topic] = (counts[topic] ?? 0) + 1;
    if (message.logTime < last) throw new Error("messages out of log-time order");
    last = message.logTime;
  }
  const metadata = [];
  for await (const record of reader.readMetadata()) metadata.push(record.name);
  console.log(JSON.stringify({ counts, metadata, statistics: Number(reader.statistics?.messageCount ?? -1) }));
} finally {
  await handle.close();
}
