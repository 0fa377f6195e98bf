// node validate-gltf.mjs FILE...: the Khronos glTF-Validator's report of each file,
// one JSON line a file ({"path", "issues"}), as tests/test_gltf_validator.py reads it.
import { readFile } from 'node:fs/promises';
import validator from 'gltf-validator';

for ( const path of process.argv.slice( 2 ) ) {
	const bytes = new Uint8Array( await readFile( path ) );
	const report = await validator.validateBytes( bytes, { maxIssues: 100, uri: path } );
	console.log( JSON.stringify( { path, issues: report.issues } ) );
}
