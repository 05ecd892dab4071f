// Validate glTF/GLB files with the Khronos glTF-Validator; print one JSON report per file.
// usage: node validate.mjs FILE...   (a .gltf's relative URIs are read beside it)
import { readFile } from "node:fs/promises";
import path from "node:path";
import { createRequire } from "node:module";

const validator = createRequire(import.meta.url)("gltf-validator");

async function validate(file) {
  const data = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(data, {
    uri: path.basename(file),
    maxIssues: 50,
    externalResourceFunction: (uri) =>
      readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
  });
  return {
    file,
    errors: report.issues.numErrors,
    warnings: report.issues.numWarnings,
    infos: report.issues.numInfos,
    messages: report.issues.messages.map((m) => `${m.severity} ${m.code} ${m.pointer ?? ""}: ${m.message}`),
  };
}

const out = [];
for (const file of process.argv.slice(2)) out.push(await validate(file));
console.log(JSON.stringify(out));
