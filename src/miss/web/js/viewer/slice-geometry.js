// The arithmetic of the linked slices (linked-slices.js), apart from the page: which
// voxel axes an axial, coronal or sagittal view shows and which way round, read from
// the scan's own voxel -> patient LPS mm affine; a slice's pixels under a window; a
// surface's outline on a slice plane.

// Each view in radiological orientation, as patient LPS directions: the screen's right,
// the screen's down and the slice's normal. Axial: the patient's left on the screen's
// right, posterior down (seen from the feet); coronal: left on the right, inferior down
// (seen from the front); sagittal: posterior on the right, inferior down.
export const VIEWS = {
	axial: { right: [ 1, 0, 0 ], down: [ 0, 1, 0 ], normal: [ 0, 0, 1 ] },
	coronal: { right: [ 1, 0, 0 ], down: [ 0, 0, - 1 ], normal: [ 0, 1, 0 ] },
	sagittal: { right: [ 0, 1, 0 ], down: [ 0, 0, - 1 ], normal: [ 1, 0, 0 ] },
};

const dot = ( a, b ) => a[ 0 ] * b[ 0 ] + a[ 1 ] * b[ 1 ] + a[ 2 ] * b[ 2 ];
const norm = ( a ) => Math.hypot( ...a );

// The patient direction a vector points to most: 'L' | 'R' | 'P' | 'A' | 'S' | 'I'.
export function letter( lps ) {
	const axis = [ 0, 1, 2 ].reduce( ( best, i ) => ( Math.abs( lps[ i ] ) > Math.abs( lps[ best ] ) ? i : best ), 0 );
	return [ [ 'R', 'L' ], [ 'A', 'P' ], [ 'I', 'S' ] ][ axis ][ lps[ axis ] > 0 ? 1 : 0 ];
}

// The affine {m: 3x3 (columns: a voxel step along i, j, k in LPS mm), t: LPS mm of voxel
// (0, 0, 0), inv: m's inverse} from the header's 4x4, row-major.
export function frameOf( affine ) {
	const m = [ 0, 1, 2 ].map( ( r ) => affine[ r ].slice( 0, 3 ) );
	const t = [ 0, 1, 2 ].map( ( r ) => affine[ r ][ 3 ] );
	const [ [ a, b, c ], [ d, e, f ], [ g, h, i ] ] = m;
	const det = a * ( e * i - f * h ) - b * ( d * i - f * g ) + c * ( d * h - e * g );
	const inv = [
		[ e * i - f * h, c * h - b * i, b * f - c * e ],
		[ f * g - d * i, a * i - c * g, c * d - a * f ],
		[ d * h - e * g, b * g - a * h, a * e - b * d ],
	].map( ( row ) => row.map( ( x ) => x / det ) );
	return { m, t, inv };
}

export const toVoxel = ( frame, lps ) => frame.inv.map( ( row ) => dot( row, [ 0, 1, 2 ].map( ( r ) => lps[ r ] - frame.t[ r ] ) ) );
export const toLps = ( frame, ijk ) => frame.m.map( ( row, r ) => dot( row, ijk ) + frame.t[ r ] );

// How a view shows the grid: the voxel axis across the slice (s), the one along the
// screen's right (u) and down (v), whether each runs against the screen, their sizes and
// steps (mm), and the edge labels the affine gives them (not assumed: an oblique or
// flipped scan says what its edges are).
export function layoutOf( frame, dims, name ) {
	const view = VIEWS[ name ];
	const column = ( axis ) => frame.m.map( ( row ) => row[ axis ] );
	const along = ( axis, dir ) => Math.abs( dot( column( axis ), dir ) ) / norm( column( axis ) );
	const s = [ 0, 1, 2 ].reduce( ( best, a ) => ( along( a, view.normal ) > along( best, view.normal ) ? a : best ), 0 );
	const rest = [ 0, 1, 2 ].filter( ( a ) => a !== s );
	const u = along( rest[ 0 ], view.right ) >= along( rest[ 1 ], view.right ) ? rest[ 0 ] : rest[ 1 ];
	const v = rest[ 0 ] === u ? rest[ 1 ] : rest[ 0 ];
	const flipU = dot( column( u ), view.right ) < 0;
	const flipV = dot( column( v ), view.down ) < 0;
	const right = column( u ).map( ( x ) => ( flipU ? - x : x ) );
	const down = column( v ).map( ( x ) => ( flipV ? - x : x ) );
	const opposite = ( d ) => d.map( ( x ) => - x );
	return {
		s, u, v, flipU, flipV, count: dims[ s ], nU: dims[ u ], nV: dims[ v ],
		stepU: norm( column( u ) ), stepV: norm( column( v ) ),
		labels: { right: letter( right ), left: letter( opposite( right ) ), bottom: letter( down ), top: letter( opposite( down ) ) },
	};
}

// Continuous voxel coordinates <-> image coordinates (a, b: image columns and rows, voxel
// centres at integers) of a view's layout.
export function voxelToImage( layout, c ) {
	const a = layout.flipU ? layout.nU - 1 - c[ layout.u ] : c[ layout.u ];
	const b = layout.flipV ? layout.nV - 1 - c[ layout.v ] : c[ layout.v ];
	return [ a, b ];
}

export function imageToVoxel( layout, a, b, index ) {
	const c = [ 0, 0, 0 ];
	c[ layout.s ] = index;
	c[ layout.u ] = layout.flipU ? layout.nU - 1 - a : a;
	c[ layout.v ] = layout.flipV ? layout.nV - 1 - b : b;
	return c;
}

// One slice as RGBA (nU x nV, rows top to bottom) under a window (centre and width in
// the volume's units: real = scale * byte + offset).
export function slicePixels( header, data, layout, index, level, width ) {
	const grey = new Uint8ClampedArray( 256 );
	for ( let b = 0; b < 256; b ++ ) grey[ b ] = ( ( header.scale * b + header.offset - level ) / Math.max( width, 1e-6 ) + 0.5 ) * 255;
	const [ nx, ny ] = header.dims;
	const stride = [ 1, nx, nx * ny ];
	const { nU, nV } = layout;
	const out = new Uint8ClampedArray( nU * nV * 4 );
	const c = [ 0, 0, 0 ];
	c[ layout.s ] = index;
	for ( let b = 0; b < nV; b ++ ) {
		c[ layout.v ] = layout.flipV ? nV - 1 - b : b;
		for ( let a = 0; a < nU; a ++ ) {
			c[ layout.u ] = layout.flipU ? nU - 1 - a : a;
			const g = grey[ data[ c[ 0 ] * stride[ 0 ] + c[ 1 ] * stride[ 1 ] + c[ 2 ] * stride[ 2 ] ] ];
			const o = ( b * nU + a ) * 4;
			out[ o ] = out[ o + 1 ] = out[ o + 2 ] = g;
			out[ o + 3 ] = 255;
		}
	}
	return out;
}

// A surface's outline on the plane c[axis] = at (voxel coordinates): the segments
// [[c0, c1], ...] (voxel coordinates) where its triangles cross it. `voxels`: its
// vertices in voxel coordinates (Float32Array, 3 a vertex); `index`: its triangles (3
// vertex numbers each), or null for a plain list. A vertex on the plane counts as
// above it, so that each crossing is drawn once and every outline closes.
export function outline( voxels, index, axis, at ) {
	const segments = [];
	const n = index ? index.length : voxels.length / 3;
	const vertex = ( k ) => ( index ? index[ k ] : k );
	const crossing = ( p, q, dp, dq ) => {
		const t = dp / ( dp - dq );
		return [ 0, 1, 2 ].map( ( r ) => voxels[ 3 * p + r ] + t * ( voxels[ 3 * q + r ] - voxels[ 3 * p + r ] ) );
	};
	for ( let k = 0; k < n; k += 3 ) {
		const tri = [ vertex( k ), vertex( k + 1 ), vertex( k + 2 ) ];
		const d = tri.map( ( p ) => voxels[ 3 * p + axis ] - at );
		const above = d.map( ( x ) => x >= 0 );
		if ( above[ 0 ] === above[ 1 ] && above[ 1 ] === above[ 2 ] ) continue;
		const ends = [];
		for ( let e = 0; e < 3; e ++ ) {
			const f = ( e + 1 ) % 3;
			if ( above[ e ] !== above[ f ] ) ends.push( crossing( tri[ e ], tri[ f ], d[ e ], d[ f ] ) );
		}
		if ( Math.hypot( ends[ 0 ][ 0 ] - ends[ 1 ][ 0 ], ends[ 0 ][ 1 ] - ends[ 1 ][ 1 ], ends[ 0 ][ 2 ] - ends[ 1 ][ 2 ] ) > 1e-6 ) segments.push( ends );
	}
	return segments;
}

// The parts of `segments` ([[c0, c1], ...], voxel coordinates) on the kept side of a
// plane: `keep(c)` its signed distance, kept where >= 0 (the 3-D view's clipping plane,
// in voxel coordinates); a segment that crosses it is cut where it does.
export function clipSegments( segments, keep ) {
	const kept = [];
	for ( const [ p, q ] of segments ) {
		const [ dp, dq ] = [ keep( p ), keep( q ) ];
		if ( dp >= 0 && dq >= 0 ) kept.push( [ p, q ] );
		else if ( dp >= 0 || dq >= 0 ) {
			const t = dp / ( dp - dq );
			const cut = [ 0, 1, 2 ].map( ( r ) => p[ r ] + t * ( q[ r ] - p[ r ] ) );
			kept.push( dp >= 0 ? [ p, cut ] : [ cut, q ] );
		}
	}
	return kept;
}
