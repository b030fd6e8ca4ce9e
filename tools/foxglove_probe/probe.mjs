// A Foxglove app's side of the protocol, for uav_vs's tests: connect to a server, take
// its advertisements, subscribe to some topics, make a service call, and print what
// came back as one JSON document on stdout.
//
//   node probe.mjs '{"url": "ws://127.0.0.1:8765", "subscribe": {"/ground/pose": 5},
//                    "timeout_s": 20,
//                    "call": {"service": "/arm", "data_b64": "AAEAAAE="}}'
//
// "call" may name a service by "service_id" instead (a call to a service the server never
// advertised). "watch" (a regular expression) subscribes to every topic it matches, as
// they are advertised, and only counts their messages and bytes ("watched"); the run then
// ends after "timeout_s", on SIGTERM or when the server goes, with "bytesRead", all the
// connection carried, over "seconds" from the server's first message. The run ends once every subscribed topic has its count of messages and the call
// is answered, or after "timeout_s"; "settle_s" (default 1) is how long to wait for the
// advertisements before subscribing and calling (a topic or the service named, advertised
// later, is subscribed or called then).
import protocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = protocol;

const spec = JSON.parse(process.argv[2]);
const wanted = spec.subscribe ?? {};    // topic -> messages to wait for
const watch = spec.watch === undefined ? null : new RegExp(`^(?:${spec.watch})$`);
const subscribed = (topic) => topic in wanted || (watch !== null && watch.test(topic));
const out = {
  serverInfo: null, channels: [], services: [], messages: {}, watched: {}, statuses: [],
  serviceResponses: [], serviceFailures: [], timedOut: false, bytesRead: 0,
};
const topicOf = new Map();   // subscription id -> topic
let started = false;
let called = spec.call === undefined;

const b64 = (view) => Buffer.from(view.buffer, view.byteOffset, view.byteLength).toString("base64");
// foxglove-sdk servers speak the protocol under the name the Foxglove app asks for now,
// foxglove.sdk.v1 (the same messages as ws-protocol's foxglove.websocket.v1).
const ws = new WebSocket(spec.url, ["foxglove.sdk.v1"]);
const client = new FoxgloveClient({ ws });

let finished = false;
function finish() {
  if (finished) return;
  finished = true;
  out.bytesRead = ws._socket?.bytesRead ?? out.bytesRead;
  out.seconds = connected === null ? 0 : (Date.now() - connected) / 1000;
  client.close();
  // Exit once the whole document is written: a pipe takes it in pieces.
  process.stdout.write(JSON.stringify(out) + "\n", () => process.exit(0));
}

function done() {
  const counted = Object.entries(wanted).every(([t, n]) => (out.messages[t]?.length ?? 0) >= n);
  return started && counted && called && watch === null;
}

function subscribe(channels) {
  for (const channel of channels) {
    if (subscribed(channel.topic)) {
      topicOf.set(client.subscribe(channel.id), channel.topic);
    }
  }
}

function start() {
  started = true;
  subscribe(out.channels);
  call();
  if (done()) finish();
}

let sent = false;
function call() {    // once started, and the service named is advertised (or given by id)
  if (spec.call === undefined || sent || !started) return;
  const service = out.services.find((s) => s.name === spec.call.service);
  const serviceId = spec.call.service_id ?? service?.id;
  if (serviceId === undefined) return;
  sent = true;
  client.sendServiceCallRequest({
    serviceId, callId: 1, encoding: spec.call.encoding ?? "cdr",
    data: new Uint8Array(Buffer.from(spec.call.data_b64, "base64")),
  });
}

let connected = null;    // Date.now() at the server's first message
client.on("serverInfo", (info) => {
  out.serverInfo = info;
  connected = Date.now();
  setTimeout(start, 1000 * (spec.settle_s ?? 1));
});
client.on("advertise", (channels) => {
  out.channels.push(...channels);
  if (started) subscribe(channels);
});
client.on("unadvertise", (ids) => {
  out.channels = out.channels.filter((c) => !ids.includes(c.id));
});
client.on("advertiseServices", (services) => {
  out.services.push(...services);
  call();
});
client.on("status", (status) => {
  out.statuses.push(status);
  // foxglove-sdk 0.30 advertises a new channel before it can take subscriptions to it: a
  // subscription made at once may be refused ("Unknown channel"). Subscribe again.
  const refused = /Unknown channel\D*(\d+)/.exec(status.message);
  const channel = refused && out.channels.find((c) => c.id === Number(refused[1]));
  if (channel && subscribed(channel.topic)) {
    setTimeout(() => subscribe([channel]), 100);
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = topicOf.get(subscriptionId);
  out.bytesRead = ws._socket?.bytesRead ?? out.bytesRead;
  if (topic in wanted) {
    (out.messages[topic] ??= []).push({ timestamp: timestamp.toString(), data_b64: b64(data) });
  } else {
    const count = (out.watched[topic] ??= { messages: 0, bytes: 0 });
    count.messages += 1;
    count.bytes += data.byteLength;
  }
  if (done()) finish();
});
client.on("serviceCallResponse", (response) => {
  out.serviceResponses.push({
    serviceId: response.serviceId, callId: response.callId,
    encoding: response.encoding, data_b64: b64(response.data),
  });
  called = true;
  if (done()) finish();
});
client.on("serviceCallFailure", (failure) => {
  out.serviceFailures.push(failure);
  called = true;
  if (done()) finish();
});
client.on("error", (err) => {
  process.stderr.write(`probe: ${err?.message ?? err}\n`);
});
client.on("close", () => finish());
setTimeout(() => { out.timedOut = true; finish(); }, 1000 * (spec.timeout_s ?? 20));
process.on("SIGTERM", finish);
