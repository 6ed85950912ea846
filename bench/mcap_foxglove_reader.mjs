// Reads a recording.mcap the way Foxglove's app does, to check that it opens there as is:
//   npm install @mcap/core @foxglove/wasm-zstd @foxglove/wasm-lz4 protobufjs
//   node bench/mcap_foxglove_reader.mjs out/paper_tracking/recording.mcap
// Prints the message count per topic and the first pose; fails on any message it cannot decode.
import { McapIndexedReader } from "@mcap/core";
import zstd from "@foxglove/wasm-zstd";
import lz4 from "@foxglove/wasm-lz4";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import { open } from "node:fs/promises";

const path = process.argv[2];
const handle = await open(path, "r");
const size = (await handle.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buffer = new Uint8Array(Number(length));
    await handle.read(buffer, 0, Number(length), Number(offset));
    return buffer;
  },
};
await zstd.isLoaded; await lz4.isLoaded;
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: {
    zstd: (data, size) => zstd.decompress(data, Number(size)),
    lz4: (data, size) => lz4(data, Number(size)),
  },
});
const decoders = new Map();
for (const [id, channel] of reader.channelsById) {
  const schema = reader.schemasById.get(channel.schemaId);
  if (channel.messageEncoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(schema.data);
    const root = protobuf.Root.fromDescriptor(set);
    const type = root.lookupType(schema.name);
    decoders.set(id, (data) => type.toObject(type.decode(data), { longs: Number }));
  } else if (channel.messageEncoding === "json") {
    decoders.set(id, (data) => JSON.parse(new TextDecoder().decode(data)));
  } else {
    throw new Error(`unknown encoding ${channel.messageEncoding} on ${channel.topic}`);
  }
}
const counts = {};
let first = {};
for await (const message of reader.readMessages()) {
  const channel = reader.channelsById.get(message.channelId);
  const decoded = decoders.get(message.channelId)(message.data);
  counts[channel.topic] = (counts[channel.topic] ?? 0) + 1;
  if (!(channel.topic in first)) first[channel.topic] = decoded;
}
console.log(JSON.stringify({ profile: reader.header.profile, counts }, null, 1));
console.log("first /vehicles/1/pose:", JSON.stringify(first["/vehicles/1/pose"]));
console.log("first /vehicles/1/state keys:", Object.keys(first["/vehicles/1/state"] ?? {}).join(","));
