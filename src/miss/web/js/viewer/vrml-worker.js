// Reads a VRML file MISS wrote, off the page's thread: a 2 M-triangle model's 98 MB of
// text had held the page 13.6 s in three.js's VRMLLoader. MISS's writer (miss.export.vrml)
// puts each part in a Shape: a Material's diffuseColor and transparency, then an
// IndexedFaceSet's Coordinate points, Normal vectors and coordIndex, as plain numbers.
// This reads exactly that, into typed arrays handed back without a copy; a file it does
// not recognise is answered { unknown: true }, and the page reads it with VRMLLoader.
//
// Message in: { url }. Out: { progress: [loaded, total] } while it arrives, then
// { parts: [ { name, color: [r, g, b], opacity, positions, normals, indices } ] },
// { unknown: true } or { error }.

const SEPARATORS = new Set( [ 32, 44, 10, 13, 9 ] ); // space , \n \r \t

// The numbers of text[from, to) (a VRML MF field's body) into a typed array of Type.
export function numbers( text, from, to, Type ) {
	let out = new Type( Math.max( 16, ( to - from ) >> 2 ) );
	let n = 0;
	let i = from;
	while ( i < to ) {
		let c = text.charCodeAt( i );
		if ( SEPARATORS.has( c ) ) {
			i ++;
			continue;
		}
		const start = i;
		let sign = 1;
		if ( c === 45 || c === 43 ) {
			sign = c === 45 ? - 1 : 1;
			c = text.charCodeAt( ++ i );
		}
		let value = 0;
		while ( c >= 48 && c <= 57 ) {
			value = value * 10 + c - 48;
			c = text.charCodeAt( ++ i );
		}
		if ( c === 46 ) {
			let scale = 1;
			c = text.charCodeAt( ++ i );
			while ( c >= 48 && c <= 57 ) {
				scale /= 10;
				value += ( c - 48 ) * scale;
				c = text.charCodeAt( ++ i );
			}
		}
		if ( c === 101 || c === 69 ) { // an exponent: rare in MISS's files, read exactly
			let j = i + 1;
			while ( j < to && ! SEPARATORS.has( text.charCodeAt( j ) ) ) j ++;
			value = Math.abs( Number( text.slice( start, j ) ) );
			i = j;
		}
		if ( i === start || ( i === start + 1 && sign === - 1 ) ) throw new Error( `not a number at ${start}` );
		if ( n === out.length ) {
			const grown = new Type( out.length * 2 );
			grown.set( out );
			out = grown;
		}
		out[ n ++ ] = sign * value;
	}
	return out.subarray( 0, n );
}

// Triangles from coordIndex (faces ended by -1; a polygon of more than three corners
// is fanned, as VRML's convex faces allow).
export function triangles( index ) {
	const out = [];
	let first = 0;
	for ( let i = 0; i <= index.length; i ++ ) {
		if ( i < index.length && index[ i ] >= 0 ) continue;
		for ( let k = first + 1; k + 1 < i; k ++ ) out.push( index[ first ], index[ k ], index[ k + 1 ] );
		first = i + 1;
	}
	return Uint32Array.from( out );
}

// The body of the MF field that follows `opening` from `at`: [start, end) within [ ].
function field( text, opening, at ) {
	const head = text.indexOf( opening, at );
	if ( head < 0 ) return null;
	const start = text.indexOf( '[', head ) + 1;
	const end = text.indexOf( ']', start );
	return start > 0 && end > 0 ? [ start, end ] : null;
}

// Every Shape of a MISS-written file, or null when it is not one.
export function parse( text ) {
	if ( ! text.startsWith( '#VRML V2.0' ) || ! text.includes( '# Written by MISS.' ) ) return null;
	const parts = [];
	let at = text.indexOf( 'Shape {' );
	while ( at >= 0 ) {
		const next = text.indexOf( 'Shape {', at + 1 );
		const upto = next < 0 ? text.length : next;
		parts.push( shape( text, at, upto, parts.length ) );
		if ( ! parts[ parts.length - 1 ] ) return null;
		at = next;
	}
	return parts.length ? parts : null;
}

// The part's name: the comment MISS writes before its DEF (the full name, not the DEF's
// letters and digits), without "(label N)"; else the DEF's; else its number.
function nameOf( text, at, n ) {
	const def = text.lastIndexOf( 'DEF ', at );
	if ( def < 0 || def < text.lastIndexOf( '}', at ) ) return `part ${n + 1}`;
	const line = text.lastIndexOf( '\n# ', def );
	const comment = line >= 0 && text.indexOf( '\n', line + 1 ) === def - 1 ? text.slice( line + 3, def - 1 ) : '';
	return comment.replace( / \(label \d+\)$/, '' ).trim() || text.slice( def + 4, at ).trim();
}

// One Shape of text[at, upto), or null when it is not as MISS writes them.
function shape( text, at, upto, n ) {
	const name = nameOf( text, at, n );
	const colour = /diffuseColor\s+(\S+)\s+(\S+)\s+(\S+)/.exec( text.slice( at, Math.min( upto, at + 400 ) ) );
	const clear = /transparency\s+(\S+)/.exec( text.slice( at, Math.min( upto, at + 400 ) ) );
	const point = field( text, 'point [', at );
	const vector = field( text, 'vector [', at );
	const coordIndex = field( text, 'coordIndex [', at );
	if ( ! colour || ! point || ! coordIndex || coordIndex[ 1 ] > upto ) return null;
	const positions = numbers( text, point[ 0 ], point[ 1 ], Float32Array );
	const normals = vector && vector[ 1 ] < coordIndex[ 0 ] ? numbers( text, vector[ 0 ], vector[ 1 ], Float32Array ) : null;
	return {
		name, color: colour.slice( 1, 4 ).map( Number ), opacity: clear ? 1 - Number( clear[ 1 ] ) : 1,
		positions: positions.slice(), normals: normals && normals.length === positions.length ? normals.slice() : null,
		indices: triangles( numbers( text, coordIndex[ 0 ], coordIndex[ 1 ], Int32Array ) ),
	};
}

async function read( url ) {
	const response = await fetch( url, { credentials: 'same-origin' } );
	if ( ! response.ok ) throw new Error( `the VRML file could not be fetched (${response.status})` );
	const total = Number( response.headers.get( 'Content-Length' ) ) || 0;
	const reader = response.body.getReader();
	const chunks = [];
	let loaded = 0;
	for ( ;; ) {
		const { done, value } = await reader.read();
		if ( done ) break;
		chunks.push( value );
		loaded += value.length;
		postMessage( { progress: [ loaded, total ] } );
	}
	const bytes = new Uint8Array( loaded );
	let offset = 0;
	for ( const c of chunks ) {
		bytes.set( c, offset );
		offset += c.length;
	}
	return new TextDecoder().decode( bytes );
}

if ( typeof WorkerGlobalScope !== 'undefined' && self instanceof WorkerGlobalScope ) {
	self.onmessage = async ( { data } ) => {
		try {
			const parts = parse( await read( data.url ) );
			if ( ! parts ) return postMessage( { unknown: true } );
			const buffers = parts.flatMap( ( p ) => [ p.positions.buffer, p.indices.buffer, ...( p.normals ? [ p.normals.buffer ] : [] ) ] );
			postMessage( { parts }, buffers );
		} catch ( err ) {
			postMessage( { error: String( err.message || err ) } );
		}
	};
}
