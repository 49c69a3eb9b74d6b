// Usage: node check.mjs LOG.mcap [MORE.mcap ...] [--paths PATH ...]
// Reads each file alone with McapIndexedReader (validating chunk CRCs), as a viewer does with files opened
// together, and prints JSON: per file its topic counts, counts per channel id, metadata names, statistics,
// schema and channel ids;
// and over all files the merged topic counts and metadata names. Every message of a protobuf channel is
// decoded with the FileDescriptorSet of its schema, as Foxglove decodes it (protobufjs: Root.fromDescriptor,
// then toObject with defaults); starlog's own messages (schema "starlog.*") are also printed, the first of
// each topic, as "first" (64-bit integers as numbers, enums by name). With --paths, each Foxglove message path
// (the subset a Plot panel's series use: topic.field, [:] and [n] of arrays, {field==value} filters) is
// evaluated on every decoded message of the files together: "paths" gives its values' count and the first
// few. Exits non-zero on any error.
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

async function readFile(path, paths = []) {
  const handle = await open(path, "r");
  try {
    const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(handle), decompressHandlers });
    const counts = {};
    const channelCounts = {};
    const decoded = {};
    const first = {};
    const decoders = new Map();
    const found = {};
    const topics = [...reader.channelsById.values()].map((c) => c.topic).sort((a, b) => b.length - a.length);
    const wanted = paths.map((p) => [p, topics.find((t) => p.startsWith(`${t}.`))]).filter(([, t]) => t);
    const steps = new Map(wanted.map(([p, t]) => [p, parsePath(p.slice(t.length))]));
    let last = -1n;
    for await (const message of reader.readMessages({ validateCrcs: true })) {
      const channel = reader.channelsById.get(message.channelId);
      if (channel === undefined) throw new Error(`a message of channel ${message.channelId}, which the reader does not know`);
      const topic = channel.topic;
      counts[topic] = (counts[topic] ?? 0) + 1;
      channelCounts[message.channelId] = (channelCounts[message.channelId] ?? 0) + 1;
      if (message.logTime < last) throw new Error("messages out of log-time order");
      last = message.logTime;
      const schema = reader.schemasById.get(channel.schemaId);
      if (channel.messageEncoding === "protobuf" && schema?.encoding === "protobuf") {
        if (!decoders.has(schema.id)) decoders.set(schema.id, protobufDecoder(schema));
        const value = decoders.get(schema.id)(message.data);
        decoded[topic] = (decoded[topic] ?? 0) + 1;
        if (schema.name.startsWith("starlog.") && !(topic in first)) first[topic] = value;
        for (const [p, t] of wanted) {
          if (t !== topic) continue;
          found[p] = [...(found[p] ?? []), ...evaluate(steps.get(p), value)];
        }
      }
    }
    const metadata = [];
    for await (const record of reader.readMetadata()) metadata.push(record.name);
    return {
      path, counts, channelCounts, decoded, first, found, metadata, statistics: Number(reader.statistics?.messageCount ?? -1),
      schemaIds: [...reader.schemasById.keys()], channelIds: [...reader.channelsById.keys()],
    };
  } finally {
    await handle.close();
  }
}

// A Foxglove message path after its topic, e.g. ".tracks[:]{track==9}.x", as steps.
function parsePath(rest) {
  const steps = [];
  const pattern = /\.([A-Za-z_][A-Za-z0-9_]*)|\[(:|\d+)\]|\{([A-Za-z_][A-Za-z0-9_]*)==("[^"]*"|[^}]+)\}/y;
  let match;
  while (pattern.lastIndex < rest.length && (match = pattern.exec(rest)) !== null) {
    if (match[1] !== undefined) steps.push({ field: match[1] });
    else if (match[2] !== undefined) steps.push({ index: match[2] });
    else steps.push({ filter: match[3], value: JSON.parse(match[4]) });
  }
  if (pattern.lastIndex !== rest.length || match === null) throw new Error(`cannot parse message path ${rest}`);
  return steps;
}

function evaluate(steps, message) {
  let values = [message];
  for (const step of steps) {
    if (step.field !== undefined) values = values.filter((v) => v != null && step.field in v).map((v) => v[step.field]);
    else if (step.index === ":") values = values.flatMap((v) => (Array.isArray(v) ? v : []));
    else if (step.index !== undefined) values = values.map((v) => v[Number(step.index)]).filter((v) => v !== undefined);
    else values = values.filter((v) => v[step.filter] === step.value);
  }
  return values;
}

const args = process.argv.slice(2);
const split = args.indexOf("--paths");
const logs = split < 0 ? args : args.slice(0, split);
const paths = split < 0 ? [] : args.slice(split + 1);
const files = [];
for (const path of logs) files.push(await readFile(path, paths));
const counts = {};
for (const file of files) for (const [topic, n] of Object.entries(file.counts)) counts[topic] = (counts[topic] ?? 0) + n;
const found = {};
for (const file of files) for (const [p, values] of Object.entries(file.found)) found[p] = [...(found[p] ?? []), ...values];
for (const file of files) delete file.found;
console.log(JSON.stringify({
  files, counts, metadata: files.flatMap((f) => f.metadata),
  paths: Object.fromEntries(paths.map((p) => [p, { count: found[p]?.length ?? 0, values: (found[p] ?? []).slice(0, 5) }])),
  statistics: files.reduce((sum, f) => sum + f.statistics, 0),
}));
