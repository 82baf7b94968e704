// An independent MQTT peer for tests/mqtt: subscribes on the broker at argv[2] and prints one JSON line per
// message on stdout, decoded with Eclipse Tahu's sparkplug-payload (Sparkplug mode) or as text (JSON mode).
// In Sparkplug mode it also plays a Sparkplug host: after an NDEATH whose bdSeq matches the node's NBIRTH it
// marks every metric of the node's devices STALE and prints {"event": "stale", ...}. A line "rebirth" on stdin
// publishes an NCMD Node Control/Rebirth to the node named by argv[4]/argv[5] (group/node).
//   node peer.js mqtt://127.0.0.1:PORT sparkplug GROUP NODE
//   node peer.js mqtt://127.0.0.1:PORT json PREFIX
"use strict";
const mqtt = require("mqtt");
const readline = require("readline");
const sparkplug = require("sparkplug-payload").get("spBv1.0");

const [url, mode, a, b] = process.argv.slice(2);
const client = mqtt.connect(url, { clientId: `peer-${process.pid}`, clean: false, reconnectPeriod: 200 });
const out = (obj) => process.stdout.write(JSON.stringify(obj, plain) + "\n");

function plain(key, value) {
  if (value && typeof value === "object" && typeof value.toNumber === "function" && "low" in value) {
    return value.toNumber(); // protobufjs Long (uint64 fields)
  }
  if (value && value.type === "Buffer") return undefined;
  return value;
}

// the host's view: per node, the bdSeq of its birth; per device, its metrics and whether they are stale
const nodes = {};
const devices = {};

function host(kind, node, device, payload) {
  const bd = (payload.metrics || []).find((m) => m.name === "bdSeq");
  const bdSeq = bd ? Number(bd.value) : null;
  if (kind === "NBIRTH") nodes[node] = { bdSeq, online: true };
  if (kind === "DBIRTH") devices[`${node}/${device}`] = { stale: false, metrics: (payload.metrics || []).length };
  if (kind === "NDEATH") {
    const n = nodes[node];
    if (n && n.bdSeq === bdSeq) {
      n.online = false;
      for (const [key, d] of Object.entries(devices)) {
        if (key.startsWith(`${node}/`)) {
          d.stale = true;
          out({ event: "stale", device: key, metrics: d.metrics, bdSeq });
        }
      }
    } else {
      out({ event: "ignored-death", node, bdSeq, birthBdSeq: n ? n.bdSeq : null });
    }
  }
}

client.on("connect", () => {
  const topic = mode === "sparkplug" ? `spBv1.0/${a}/#` : `${a}/#`;
  client.subscribe(topic, { qos: 1 }, (err) => out({ event: err ? "error" : "ready", topic }));
});
client.on("error", (err) => out({ event: "error", message: String(err) }));
client.on("message", (topic, message, packet) => {
  if (mode !== "sparkplug") {
    out({ topic, retain: packet.retain, text: message.toString("utf8") });
    return;
  }
  const parts = topic.split("/");
  const kind = parts[2];
  if (kind === "NCMD" || kind === "STATE") return;
  let payload;
  try {
    payload = sparkplug.decodePayload(message);
  } catch (err) {
    out({ topic, event: "undecodable", message: String(err) });
    return;
  }
  out({ topic, kind, node: parts[3], device: parts[4] || null, payload });
  host(kind, parts[3], parts[4], payload);
});

readline.createInterface({ input: process.stdin }).on("line", (line) => {
  if (line.trim() === "rebirth") {
    const body = sparkplug.encodePayload({
      timestamp: Date.now(),
      metrics: [{ name: "Node Control/Rebirth", type: "Boolean", value: true }],
    });
    client.publish(`spBv1.0/${a}/NCMD/${b}`, body, { qos: 0 }, () => out({ event: "sent-rebirth" }));
  }
});
