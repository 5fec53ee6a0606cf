// Independent check of an MCAP capture with the official TypeScript libraries.
// Usage: node read.mjs FILE  ->  prints JSON {topics: {topic: count}, schemas: {topic: name},
// decoded: {topic: {string and number fields of the first decoded message}}, summary: bool}
// Exit code 1 when the file cannot be read or a message does not decode with its schema.
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers, protobufFromBinaryDescriptor } from "@mcap/support";

// The string and number fields of a decoded message (enough to check encodings and sizes).
function scalars(value) {
  const out = {};
  for (const [key, field] of Object.entries(value)) {
    if (typeof field === "string" || typeof field === "number") out[key] = field;
  }
  return out;
}

function decoderFor(channel, schema) {
  if (channel.messageEncoding === "protobuf") {
    if (!schema || schema.encoding !== "protobuf") {
      throw new Error(`${channel.topic}: protobuf channel without a protobuf schema`);
    }
    const type = protobufFromBinaryDescriptor(schema.data).lookupType(schema.name);
    return (data) => type.toObject(type.decode(data), { defaults: true });
  }
  if (channel.messageEncoding === "json") {
    const text = new TextDecoder();
    return (data) => JSON.parse(text.decode(data));
  }
  throw new Error(`${channel.topic}: unexpected message encoding ${channel.messageEncoding}`);
}

async function main(path) {
  const handle = await open(path, "r");
  try {
    const reader = await McapIndexedReader.Initialize({
      readable: new FileHandleReadable(handle),
      decompressHandlers: await loadDecompressHandlers(),
    });
    // One decoder per channel, built only from the schema stored in the file.
    const decoders = new Map();
    const schemas = {};
    for (const [id, channel] of reader.channelsById) {
      const schema = reader.schemasById.get(channel.schemaId);
      decoders.set(id, decoderFor(channel, schema));
      schemas[channel.topic] = schema ? schema.name : null;
    }
    const topics = {};
    const decoded = {};
    for await (const message of reader.readMessages()) {
      const channel = reader.channelsById.get(message.channelId);
      topics[channel.topic] = (topics[channel.topic] ?? 0) + 1;
      const value = decoders.get(message.channelId)(message.data);
      if (value === undefined || value === null) {
        throw new Error(`${channel.topic}: message did not decode`);
      }
      decoded[channel.topic] ??= scalars(value);
    }
    const summary = reader.chunkIndexes.length > 0;
    console.log(JSON.stringify({ topics, schemas, decoded, summary }));
  } finally {
    await handle.close();
  }
}

main(process.argv[2]).catch((err) => {
  console.error(String(err?.stack ?? err));
  process.exit(1);
});
