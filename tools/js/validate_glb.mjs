// Validate a .glb with the Khronos glTF validator; print its report summary as JSON.
// Usage: node validate_glb.mjs FILE.glb [--full]
// Exit code: 0 = no errors, 1 = the validator found errors, 2 = usage / unreadable file.
import { readFileSync } from "node:fs";
import { basename } from "node:path";
import validator from "gltf-validator";

const args = process.argv.slice(2);
const file = args.find((a) => !a.startsWith("--"));
if (!file) {
  console.error("usage: node validate_glb.mjs FILE.glb [--full]");
  process.exit(2);
}
let bytes;
try {
  bytes = new Uint8Array(readFileSync(file));
} catch (err) {
  console.error(`error: ${file}: ${err.message}`);
  process.exit(2);
}
const report = await validator.validateBytes(bytes, {
  uri: basename(file),
  maxIssues: 200,
  // A .glb written by t2bs is self-contained: any external resource is itself an error.
  externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri} not allowed`)),
});
const issues = report.issues;
const out = {
  file,
  errors: issues.numErrors,
  warnings: issues.numWarnings,
  infos: issues.numInfos,
  hints: issues.numHints,
  messages: issues.messages
    .filter((m) => args.includes("--full") || m.severity <= 1)
    .map((m) => ({ code: m.code, severity: m.severity, message: m.message, pointer: m.pointer })),
  info: {
    version: report.info && report.info.version,
    generator: report.info && report.info.generator,
    maxAttributes: report.info && report.info.maxAttributes,
    animationCount: report.info && report.info.animationCount,
    totalVertexCount: report.info && report.info.totalVertexCount,
  },
};
console.log(JSON.stringify(out, null, 2));
process.exit(issues.numErrors > 0 ? 1 : 0);
