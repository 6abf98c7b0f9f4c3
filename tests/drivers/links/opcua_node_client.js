// The OPC 40100 PLC sequence with node-opcua's client (a stack that shares no code with the
// server): tests/drivers/links/test_opcua_node.py runs it with NODE_PATH at a node-opcua-client
// install and reads the one JSON object it prints. Usage: node opcua_node_client.js URL PARTS
"use strict";
const {
    OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, VariantArrayType,
    makeBrowsePath, ClientSubscription, ClientMonitoredItem, TimestampsToReturn,
    constructEventFilter, coerceNodeId, BrowseDirection,
} = require("node-opcua-client");

const MV = "http://opcfoundation.org/UA/MachineVision";
const INSTANCE = "urn:vgripd:vision-system";

async function main() {
    const [url, partsText] = process.argv.slice(2);
    const parts = Number(partsText);
    const out = { refused: {}, jobs: [], ok: false };
    const client = OPCUAClient.create({
        endpointMustExist: false, securityMode: MessageSecurityMode.None,
        securityPolicy: SecurityPolicy.None, connectionStrategy: { maxRetry: 2 },
    });
    await client.connect(url);
    const session = await client.createSession();
    try {
        const namespaces = await session.readNamespaceArray();
        const mv = namespaces.indexOf(MV);
        const idx = namespaces.indexOf(INSTANCE);
        out.namespaces = { mv, idx };
        // the type hierarchy from the official NodeSet: BaseObjectType -> VisionSystemType
        const typePath = await session.translateBrowsePath(
            makeBrowsePath("i=58", `/${mv}:VisionSystemType`));
        out.visionSystemType = typePath.targets[0].targetId.toString();
        const vs = coerceNodeId(`ns=${idx};s=VisionSystem`);
        const typeDef = await session.browse({
            nodeId: vs, referenceTypeId: "HasTypeDefinition",
            browseDirection: BrowseDirection.Forward });
        out.instanceType = typeDef.references[0].nodeId.toString();
        const node = async (path) => {
            const r = await session.translateBrowsePath(makeBrowsePath(vs, path));
            return r.targets[0].targetId;
        };
        const ext = (id, fields) => session.constructExtensionObject(
            coerceNodeId(`ns=${mv};i=${id}`), fields);
        const sm = await node(`/${mv}:VisionStateMachine`);
        const auto = await node(`/${mv}:VisionStateMachine/${mv}:AutomaticModeStateMachine`);
        const call = async (objectId, methodPath, inputArguments) => {
            const methodId = await node(methodPath);
            const r = await session.call({ objectId, methodId, inputArguments });
            return r;
        };
        const state = async () => {
            const top = await session.read({
                nodeId: await node(`/${mv}:VisionStateMachine/0:CurrentState`),
                attributeId: AttributeIds.Value });
            const a = await session.read({
                nodeId: await node(`/${mv}:VisionStateMachine/${mv}:AutomaticModeStateMachine/0:CurrentState`),
                attributeId: AttributeIds.Value });
            return [top.value.value.text, a.value.value ? a.value.value.text || "" : ""];
        };
        const jobArgs = async (meas, part) => [
            { dataType: DataType.ExtensionObject, value: await ext(3015, { id: meas }) },
            { dataType: DataType.ExtensionObject, value: await ext(3004, { id: part }) },
            { dataType: DataType.ExtensionObject, value: await ext(3002, { id: "" }) },
            { dataType: DataType.ExtensionObject, value: await ext(3003, { id: "" }) },
            { dataType: DataType.Variant, arrayType: VariantArrayType.Array, value: [] },
        ];
        const startPath = `/${mv}:VisionStateMachine/${mv}:AutomaticModeStateMachine/${mv}:StartSingleJob`;
        out.states = [await state()];
        out.refused.preoperational = (await call(auto, startPath, await jobArgs("m", "p"))).statusCode.name;
        const sel = await call(sm, `/${mv}:VisionStateMachine/${mv}:SelectModeAutomatic`, []);
        out.select = sel.statusCode.name;
        out.states.push(await state());
        out.refused.initialized = (await call(auto, startPath, await jobArgs("m", "p"))).statusCode.name;
        const rm = await node(`/${mv}:RecipeManagement`);
        const prep = await call(rm, `/${mv}:RecipeManagement/${mv}:PrepareRecipe`, [
            { dataType: DataType.ExtensionObject, value: await ext(3002, { id: "0" }) },
            { dataType: DataType.ExtensionObject, value: await ext(3013, { id: "" }) },
        ]);
        out.prepare = prep.statusCode.name;
        if (prep.outputArguments && prep.outputArguments.length) {
            const internal = prep.outputArguments[0].value;
            out.prepared = { id: internal.id, type: internal.schema ? internal.schema.name : "?" };
        }
        out.states.push(await state());

        const subscription = ClientSubscription.create(session, {
            requestedPublishingInterval: 20, requestedMaxKeepAliveCount: 50,
            requestedLifetimeCount: 500, publishingEnabled: true });
        const fields = ["EventType", `${mv}:ResultId`, `${mv}:JobId`, `${mv}:ResultState`,
                        `${mv}:MeasId`, `${mv}:PartId`];
        const item = ClientMonitoredItem.create(subscription,
            { nodeId: vs, attributeId: AttributeIds.EventNotifier },
            { queueSize: 100, filter: constructEventFilter(fields) }, TimestampsToReturn.Both);
        const events = [];
        let wake = null;
        item.on("changed", (values) => {
            if (values[0].value.toString() === `ns=${mv};i=1024`) {
                events.push(values);
                if (wake) { wake(); }
            }
        });
        await new Promise((resolve) => item.on("initialized", resolve));
        const rsm = await node(`/${mv}:ResultManagement`);
        for (let n = 1; n <= parts; n++) {
            const r = await call(auto, startPath, await jobArgs(`m${n}`, `p${n}`));
            if (!r.outputArguments || !r.outputArguments.length) {
                throw new Error(`StartSingleJob ${n}: ${r.statusCode.toString()} ${JSON.stringify(out)}`);
            }
            const jobId = r.outputArguments[0].value.id;
            const deadline = Date.now() + 60000;
            while (events.length < n && Date.now() < deadline) {
                await new Promise((resolve) => { wake = resolve; setTimeout(resolve, 200); });
            }
            const ev = events[n - 1];
            const resultId = ev[1].value;
            const got = await call(rsm, `/${mv}:ResultManagement/${mv}:GetResultById`, [
                { dataType: DataType.ExtensionObject, value: resultId },
                { dataType: DataType.Double, value: 1000 },
            ]);
            const result = got.outputArguments[1].value;
            const content = {};
            for (const v of result.resultContent || []) {
                const kv = v.value;
                content[kv.key.name] = kv.value.value instanceof Float64Array
                    ? Array.from(kv.value.value) : kv.value.value;
            }
            out.jobs.push({
                status: r.statusCode.name, jobId, eventJobId: ev[2].value.id,
                eventResultState: ev[3].value, eventMeasId: ev[4].value.id,
                eventPartId: ev[5].value.id, resultStatus: got.statusCode.name,
                resultJobId: result.jobId.id, resultState: result.resultState,
                partId: result.partId.id, values: content.Values, statusName: content.StatusName,
                daemonJobId: content.DaemonJobId,
            });
        }
        await subscription.terminate();
        out.states.push(await state());
        out.refused.stopInReady = (await call(auto,
            `/${mv}:VisionStateMachine/${mv}:AutomaticModeStateMachine/${mv}:Stop`, [
                { dataType: DataType.Int32, value: 0 }, { dataType: DataType.String, value: "" },
            ])).statusCode.name;
        out.ok = true;
    } finally {
        await session.close();
        await client.disconnect();
        process.stdout.write("RESULT " + JSON.stringify(out) + "\n");
    }
}

main().catch((err) => { process.stderr.write(String(err && err.stack || err) + "\n"); process.exit(1); });
