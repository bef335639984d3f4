#!/usr/bin/env node
// Validates a .gltf (and the buffers and images it points to) with the Khronos glTF
// validator (npm package gltf-validator); prints its JSON report's issue counts.
// usage: NODE_PATH=<dir with node_modules> node validate_gltf.js FILE.gltf
// exit 0: no errors and no warnings; 1: otherwise.
const fs = require("fs");
const path = require("path");
const validator = require("gltf-validator");

const file = process.argv[2];
const dir = path.dirname(file);
validator
  .validateBytes(new Uint8Array(fs.readFileSync(file)), {
    uri: path.basename(file),
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        fs.readFile(path.join(dir, decodeURIComponent(uri)), (err, data) =>
          err ? reject(err.toString()) : resolve(new Uint8Array(data))
        );
      }),
  })
  .then((report) => {
    const issues = report.issues;
    console.log(
      JSON.stringify({
        errors: issues.numErrors,
        warnings: issues.numWarnings,
        infos: issues.numInfos,
        hints: issues.numHints,
        messages: issues.messages,
        extensions: report.info && report.info.extensionsUsed,
      })
    );
    process.exit(issues.numErrors === 0 && issues.numWarnings === 0 ? 0 : 1);
  })
  .catch((e) => {
    console.error("validator failed: " + e);
    process.exit(2);
  });
