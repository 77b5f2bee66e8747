// Validates a .glb/.gltf with the Khronos glTF-Validator (npm `gltf-validator`, see package.json).
//
//   node tests/gltf_validate.mjs FILE
//
// Prints the validator's JSON report to stdout. Exit status: 0 when the report has no errors,
// 1 when it has errors, 2 when the file or the validator could not be loaded.
import { readFileSync } from "node:fs";
import { createRequire } from "node:module";
import { basename } from "node:path";

const file = process.argv[2];
if (!file) {
  console.error("usage: node tests/gltf_validate.mjs FILE.glb");
  process.exit(2);
}

let validator;
try {
  validator = createRequire(import.meta.url)("gltf-validator");
} catch (e) {
  console.error(`cannot load the gltf-validator package (run \`npm ci\`): ${e.message}`);
  process.exit(2);
}

let bytes;
try {
  bytes = new Uint8Array(readFileSync(file));
} catch (e) {
  console.error(`cannot read ${file}: ${e.message}`);
  process.exit(2);
}

try {
  const report = await validator.validateBytes(bytes, { uri: basename(file), maxIssues: 100 });
  console.log(JSON.stringify(report, null, 2));
  process.exit(report.issues.numErrors > 0 ? 1 : 0);
} catch (e) {
  console.error(`validation of ${file} failed: ${e}`);
  process.exit(2);
}
