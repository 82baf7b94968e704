// node-opcua's client as an independent peer of spindle-chtc's OPC UA server (tests/opcua/test_opcua_node.py).
// Usage: node peer.mjs '<json>' with {url, nsUri, pki, mode: "read"|"subscribe"|"connect", security?: {cert, key,
// applicationUri}, user?, password?, paths?: [...], units?: [...], timeoutMs?}. Prints one JSON object per line:
// "read" -> {ns, browse, values: {path: {value, status, sourceTimestamp}}, units: {path: {...}}, write: status};
// "subscribe" -> {ready: true} then {change: {value, status, sourceTimestamp}} per notification;
// "connect" -> {connected: true, read: status} (or {error}).
import {
  AttributeIds,
  ClientMonitoredItem,
  ClientSubscription,
  DataType,
  MessageSecurityMode,
  OPCUACertificateManager,
  OPCUAClient,
  SecurityPolicy,
  TimestampsToReturn,
  UserTokenType,
} from "node-opcua";

const cfg = JSON.parse(process.argv[2]);
const out = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");

async function main() {
  const certificateManager = new OPCUACertificateManager({
    rootFolder: cfg.pki,
    automaticallyAcceptUnknownCertificate: true, // the server's certificate (the test trusts it)
  });
  await certificateManager.initialize();
  const options = {
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    clientCertificateManager: certificateManager,
    requestedSessionTimeout: 20000,
  };
  if (cfg.security) {
    Object.assign(options, {
      securityMode: MessageSecurityMode.SignAndEncrypt,
      securityPolicy: SecurityPolicy.Basic256Sha256,
      certificateFile: cfg.security.cert,
      privateKeyFile: cfg.security.key,
      applicationUri: cfg.security.applicationUri,
    });
  } else {
    Object.assign(options, { securityMode: MessageSecurityMode.None, securityPolicy: SecurityPolicy.None });
  }
  const client = OPCUAClient.create(options);
  await client.connect(cfg.url);
  const identity = cfg.user
    ? { type: UserTokenType.UserName, userName: cfg.user, password: cfg.password }
    : { type: UserTokenType.Anonymous };
  const session = await client.createSession(identity);
  try {
    const ns = (await session.readNamespaceArray()).indexOf(cfg.nsUri);
    const id = (path) => `ns=${ns};s=Spindle1.${path}`;
    if (cfg.mode === "connect") {
      const dv = await session.read({ nodeId: id("Status.SampleAge"), attributeId: AttributeIds.Value });
      out({ connected: true, read: dv.statusCode.name });
    } else if (cfg.mode === "read") {
      const browse = await session.browse(`ns=${ns};s=Spindle1`);
      const values = {};
      for (const path of cfg.paths) {
        const dv = await session.read({ nodeId: id(path), attributeId: AttributeIds.Value });
        values[path] = {
          value: toJson(dv.value ? dv.value.value : null),
          status: dv.statusCode.value >>> 0,
          statusName: dv.statusCode.name,
          sourceTimestamp: dv.sourceTimestamp ? dv.sourceTimestamp.toISOString() : null,
        };
      }
      const units = {};
      for (const path of cfg.units) {
        const eu = (await session.read({ nodeId: `${id(path)}.EngineeringUnits`, attributeId: AttributeIds.Value })).value.value;
        const range = (await session.read({ nodeId: `${id(path)}.EURange`, attributeId: AttributeIds.Value })).value.value;
        units[path] = {
          namespaceUri: eu.namespaceUri,
          unitId: eu.unitId,
          displayName: eu.displayName.text,
          low: range.low,
          high: range.high,
        };
      }
      let write;
      try {
        const status = await session.write({
          nodeId: id("Growth.Axial"),
          attributeId: AttributeIds.Value,
          value: { value: { dataType: DataType.Double, value: 1.0 } },
        });
        write = status.name;
      } catch (err) {
        // a refused service is a ServiceFault: "... serviceResult = BadUserAccessDenied (0x801f0000)"
        write = (/(Bad[A-Za-z]+)/.exec(String(err.message)) || [String(err.message)])[0];
      }
      out({ ns, browse: browse.references.map((r) => r.browseName.name), values, units, write });
    } else if (cfg.mode === "subscribe") {
      const sub = ClientSubscription.create(session, {
        requestedPublishingInterval: 100,
        requestedLifetimeCount: 600,
        requestedMaxKeepAliveCount: 20,
        publishingEnabled: true,
      });
      const item = ClientMonitoredItem.create(
        sub,
        { nodeId: id(cfg.paths[0]), attributeId: AttributeIds.Value },
        { samplingInterval: 100, queueSize: 10, discardOldest: true },
        TimestampsToReturn.Both,
      );
      let n = 0;
      await new Promise((resolve) => {
        item.on("changed", (dv) => {
          out({
            change: {
              value: toJson(dv.value.value),
              status: dv.statusCode.value >>> 0,
              sourceTimestamp: dv.sourceTimestamp ? dv.sourceTimestamp.toISOString() : null,
            },
          });
          n += 1;
          if (n >= cfg.changes) resolve();
        });
        out({ ready: true });
        setTimeout(resolve, cfg.timeoutMs || 20000);
      });
      await sub.terminate();
    }
  } finally {
    await session.close();
    await client.disconnect();
  }
}

function toJson(v) {
  if (v instanceof Date) return v.toISOString();
  if (ArrayBuffer.isView(v)) return Array.from(v);
  if (Array.isArray(v)) return v.map(toJson);
  if (typeof v === "bigint") return Number(v);
  if (typeof v === "number" && !Number.isFinite(v)) return null;
  return v;
}

main().then(
  () => process.exit(0),
  (err) => {
    out({ error: String(err && err.message ? err.message : err) });
    process.exit(2);
  },
);
