// node load-three.mjs WEB_NODE_MODULES FORMAT FILE...: the triangles three.js's own
// loader (STLLoader, PLYLoader, OBJLoader: what a browser viewer would use) reads from
// each file, one JSON line a file ({"path", "triangles"}).
import { readFile } from 'node:fs/promises';
import { join } from 'node:path';
import { pathToFileURL } from 'node:url';

const [ modules, format, ...paths ] = process.argv.slice( 2 );
const loaders = { stl: 'STLLoader', ply: 'PLYLoader', obj: 'OBJLoader' };
const name = loaders[ format ];
const url = pathToFileURL( join( modules, 'three', 'examples', 'jsm', 'loaders', `${name}.js` ) );
const Loader = ( await import( url.href ) )[ name ];

function triangles( geometry ) {
	return ( geometry.index ? geometry.index.count : geometry.attributes.position.count ) / 3;
}

for ( const path of paths ) {
	const bytes = await readFile( path );
	const loader = new Loader();
	let count = 0;
	if ( format === 'obj' ) {
		loader.parse( bytes.toString( 'utf8' ) ).traverse( ( o ) => {
			if ( o.isMesh ) count += triangles( o.geometry );
		} );
	} else {
		count = triangles( loader.parse( bytes.buffer.slice( bytes.byteOffset, bytes.byteOffset + bytes.byteLength ) ) );
	}
	console.log( JSON.stringify( { path, triangles: count } ) );
}
