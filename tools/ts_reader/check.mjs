// Usage: node check.mjs LOG.mcap [MORE.mcap ...]
// Reads each file alone with McapIndexedReader (validating chunk CRCs), as a viewer does with files opened
// together, and prints JSON: per file its topic counts, metadata names, statistics, schema and channel ids;
// and over all files the merged topic counts and metadata names. Every message of a protobuf channel is
// decoded with the FileDescriptorSet of its schema, as Foxglove decodes it (protobufjs: Root.fromDescriptor,
// then toObject with defaults); starlog's own messages (schema "starlog.*") are also printed, the first of
// each topic, as "first" (64-bit integers as numbers, enums by name). Exits non-zero on any error.
// Used by tests/test_typescript_reader.py.
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers, protobufFromBinaryDescriptor } from "@mcap/support";
import { open } from "node:fs/promises";

const decompressHandlers = await loadDecompressHandlers();

// One decoder per schema: the message type looked up in the schema's own FileDescriptorSet.
function protobufDecoder(schema) {
  const root = protobufFromBinaryDescriptor(schema.data);
  root.resolveAll();
  const type = root.lookupType(schema.name);
  return (data) => type.toObject(type.decode(data), { defaults: true, longs: Number, enums: String });
}

async function readFile(path) {
  const handle = await open(path, "r");
  try {
    const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(handle), decompressHandlers });
    const counts = {};
    const decoded = {};
    const first = {};
    const decoders = new Map();
    let last = -1n;
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(message.channelId);
      const topic = channel.topic;
      counts[topic] = (counts[topic] ?? 0) + 1;
      if (message.logTime < last) throw new Error("messages out of log-time order");
      last = message.logTime;
      const schema = reader.schemasById.get(channel.schemaId);
      if (channel.messageEncoding === "protobuf" && schema?.encoding === "protobuf") {
        if (!decoders.has(schema.id)) decoders.set(schema.id, protobufDecoder(schema));
        const value = decoders.get(schema.id)(message.data);
        decoded[topic] = (decoded[topic] ?? 0) + 1;
        if (schema.name.startsWith("starlog.") && !(topic in first)) first[topic] = value;
      }
    }
    const metadata = [];
    for await (const record of reader.readMetadata()) metadata.push(record.name);
    return {
      path, counts, decoded, first, metadata, statistics: Number(reader.statistics?.messageCount ?? -1),
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
