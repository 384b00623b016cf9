// Run the Khronos glTF-Validator (npm package "gltf-validator") on GLB files given as arguments.
// Prints one JSON line per file: {file, validator, errors, warnings, infos, hints, messages[]}.
// Exit status 0 when no file has errors, 1 otherwise, 2 when the validator module is missing.
// Used by tests/test_export.py; find the module through NODE_PATH.
let validator;
try {
  validator = require('gltf-validator');
} catch (e) {
  console.error('gltf-validator not found (npm install --prefix ~/.cache/triplet_cl/node gltf-validator)');
  process.exit(2);
}
const fs = require('fs');
(async () => {
  let bad = 0;
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {maxIssues: 100});
    const i = report.issues;
    console.log(JSON.stringify({
      file, validator: report.validatorVersion, errors: i.numErrors, warnings: i.numWarnings,
      infos: i.numInfos, hints: i.numHints,
      messages: i.messages.map((m) => `${m.severity}:${m.code}:${m.pointer || ''}:${m.message}`),
    }));
    if (i.numErrors) bad++;
  }
  process.exit(bad ? 1 : 0);
})();
