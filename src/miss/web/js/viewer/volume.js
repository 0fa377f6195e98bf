// The scan itself in 3-D: WebGL2 ray marching of a Data3DTexture, in the viewer's scene
// and camera, placed in patient LPS millimetres by the same matrix as the surfaces
// (viewer.lpsToWorld) after the sent grid's own voxel-to-LPS affine. Drawn only when
// the viewer renders (on demand, as the surfaces are).
//
// Built on three.js's VolumeRenderShader1 (examples/jsm/shaders/VolumeShader.js): the
// same box of voxel coordinates whose back faces start each ray towards the camera, and
// its MIP; to it are added front-to-back compositing through a 256-entry colour and
// opacity table (the transfer function, made here from a preset and the window), a ray
// that starts at the camera when the camera is inside the box, and a ray that stops at
// the opaque surfaces drawn before it (their depth, when the viewer hands it over); a ray
// that stops once 95 % opaque, and steps over bricks of 8³ voxels the window leaves
// transparent (each brick's byte range, found once; which are empty, once a window). The
// step (one voxel, two while the camera moves) is volume-pass.js's to choose.
//
// The voxels come from GET /api/volumes/{id}/voxels (miss.server.voxels): a uint32
// header length, a JSON header, uint8 voxels i fastest; real = scale * byte + offset.

import * as THREE from 'three';

// Presets in the volume's own units: points [value, r, g, b, opacity a voxel] of a
// piecewise-linear transfer function, and the window (centre, width) they were drawn for;
// the window/level control stretches the points about that centre.
const CT = {
	'CT bone': { level: 700, window: 1400, points: [ [ 150, 0.9, 0.75, 0.6, 0 ], [ 400, 0.95, 0.88, 0.75, 0.35 ], [ 1400, 1, 1, 0.95, 0.8 ] ] },
	'CT soft tissue': { level: 40, window: 400, points: [ [ - 300, 0.8, 0.5, 0.4, 0 ], [ - 100, 0.85, 0.6, 0.5, 0.03 ], [ 40, 0.85, 0.35, 0.3, 0.08 ], [ 200, 0.95, 0.85, 0.75, 0.2 ], [ 700, 1, 1, 0.95, 0.6 ] ] },
	'CT vessels': { level: 300, window: 600, points: [ [ 120, 0.6, 0.05, 0.05, 0 ], [ 250, 0.85, 0.15, 0.1, 0.25 ], [ 450, 0.95, 0.6, 0.5, 0.4 ], [ 900, 1, 1, 0.95, 0.6 ] ] },
	'CT lung': { level: - 600, window: 1200, points: [ [ - 1000, 0.3, 0.5, 0.8, 0 ], [ - 900, 0.4, 0.6, 0.9, 0.02 ], [ - 500, 0.7, 0.8, 1, 0.12 ], [ - 300, 0.8, 0.8, 0.8, 0 ] ] },
};
// Any other scan (MR, or CT not in HU): a ramp over the upper part of the default window.
function genericPreset( window ) {
	const lo = window.level - window.window / 2;
	const w = window.window;
	return { level: window.level, window: w, points: [ [ lo + 0.3 * w, 0.85, 0.75, 0.65, 0 ], [ lo + 0.6 * w, 0.95, 0.85, 0.75, 0.15 ], [ lo + w, 1, 1, 1, 0.6 ] ] };
}
const MIP = ( window ) => ( { level: window.level, window: window.window, mip: true, points: [ [ window.level - window.window / 2, 0, 0, 0, 1 ], [ window.level + window.window / 2, 1, 1, 1, 1 ] ] } );

// The presets this volume is offered: name -> preset (CT ones for a scan in HU).
export function presetsFor( header ) {
	const window = header.window || { level: header.offset + 127.5 * header.scale, window: 255 * header.scale };
	const own = header.units === 'HU' ? { ...CT } : { 'MR generic': genericPreset( window ) };
	return { ...own, MIP: MIP( header.units === 'HU' ? { level: 400, window: 1600 } : window ) };
}

// The colour and opacity of each byte (RGBA, 256 entries) for a preset at a window.
export function lookupTable( header, preset, level, width ) {
	const table = new Uint8Array( 256 * 4 );
	const pts = preset.points;
	for ( let b = 0; b < 256; b ++ ) {
		const real = header.scale * b + header.offset;
		const v = preset.level + ( real - level ) * preset.window / Math.max( width, 1e-6 );
		let i = 0;
		while ( i < pts.length - 1 && pts[ i + 1 ][ 0 ] < v ) i ++;
		const [ a, c ] = [ pts[ i ], pts[ Math.min( i + 1, pts.length - 1 ) ] ];
		const t = v <= a[ 0 ] ? 0 : v >= c[ 0 ] ? 1 : ( v - a[ 0 ] ) / ( c[ 0 ] - a[ 0 ] );
		const outside = v < pts[ 0 ][ 0 ] || ( v > pts[ pts.length - 1 ][ 0 ] && pts[ pts.length - 1 ][ 4 ] === 0 );
		for ( let k = 0; k < 4; k ++ ) table[ b * 4 + k ] = Math.round( 255 * ( outside && k === 3 ? 0 : a[ k + 1 ] + t * ( c[ k + 1 ] - a[ k + 1 ] ) ) );
	}
	return table;
}

// The body of /voxels (already inflated by the browser): {header, data: Uint8Array}.
export function decode( buffer ) {
	const n = new DataView( buffer ).getUint32( 0, true );
	const header = JSON.parse( new TextDecoder().decode( new Uint8Array( buffer, 4, n ) ) );
	return { header, data: new Uint8Array( buffer, 4 + n ) };
}

// Voxels a side of a brick: the unit of empty-space skipping. A ray crossing a brick whose
// voxels all map to zero opacity (air and soft tissue under a bone window) steps over it.
const BRICK = 8;

// The lowest and highest byte of each brick and the voxels around it (the 27 bricks
// about it, a superset of the one voxel a trilinear sample also reads): {lo, hi} of
// ceil(n / BRICK) bricks a side, i fastest. Once a volume (~50 ms for 256 x 256 x 113).
export function brickRanges( data, dims ) {
	const [ nx, ny, nz ] = dims;
	const [ bx, by, bz ] = dims.map( ( n ) => Math.ceil( n / BRICK ) );
	const lo = new Uint8Array( bx * by * bz ).fill( 255 );
	const hi = new Uint8Array( bx * by * bz );
	for ( let k = 0; k < nz; k ++ ) {
		for ( let j = 0; j < ny; j ++ ) {
			const row = ( j + ny * k ) * nx;
			const brow = ( ( ( j / BRICK ) | 0 ) + by * ( ( k / BRICK ) | 0 ) ) * bx;
			for ( let b = 0; b < bx; b ++ ) {
				let l = lo[ brow + b ], h = hi[ brow + b ];
				for ( let i = b * BRICK, end = Math.min( i + BRICK, nx ); i < end; i ++ ) {
					const v = data[ row + i ];
					if ( v < l ) l = v;
					if ( v > h ) h = v;
				}
				lo[ brow + b ] = l;
				hi[ brow + b ] = h;
			}
		}
	}
	return { lo: dilate( lo, [ bx, by, bz ], Math.min ), hi: dilate( hi, [ bx, by, bz ], Math.max ), dims: [ bx, by, bz ] };
}

// Each brick's value combined (op) with its 26 neighbours', one axis at a time.
function dilate( values, dims, op ) {
	let src = values;
	for ( let axis = 0; axis < 3; axis ++ ) {
		const stride = [ 1, dims[ 0 ], dims[ 0 ] * dims[ 1 ] ][ axis ];
		const out = src.slice();
		for ( let n = 0; n < src.length; n ++ ) {
			const c = ( ( n / stride ) | 0 ) % dims[ axis ];
			if ( c > 0 ) out[ n ] = op( out[ n ], src[ n - stride ] );
			if ( c < dims[ axis ] - 1 ) out[ n ] = op( out[ n ], src[ n + stride ] );
		}
		src = out;
	}
	return src;
}

// 255 where a brick holds a byte the table gives any opacity, else 0 (all 255 for MIP,
// whose rays look at every voxel).
export function occupancy( ranges, table, mip ) {
	const seen = new Uint32Array( 257 ); // seen[b + 1]: bytes <= b with opacity
	for ( let b = 0; b < 256; b ++ ) seen[ b + 1 ] = seen[ b ] + ( table[ b * 4 + 3 ] > 0 ? 1 : 0 );
	const out = new Uint8Array( ranges.lo.length );
	for ( let n = 0; n < out.length; n ++ ) {
		out[ n ] = mip || seen[ ranges.hi[ n ] + 1 ] > seen[ ranges.lo[ n ] ] ? 255 : 0;
	}
	return out;
}

const vertexShader = /* glsl */`
	varying vec3 v_position;
	varying vec3 v_cameraInObj;
	varying vec3 v_viewDirInObj;
	varying vec4 v_clip;
	void main() {
		v_position = position;
		v_cameraInObj = ( inverse( modelMatrix ) * vec4( cameraPosition, 1.0 ) ).xyz;
		v_viewDirInObj = ( inverse( modelViewMatrix ) * vec4( 0.0, 0.0, - 1.0, 0.0 ) ).xyz;
		gl_Position = projectionMatrix * modelViewMatrix * vec4( position, 1.0 );
		v_clip = gl_Position;
	}`;

const fragmentShader = /* glsl */`
	precision highp float;
	precision mediump sampler3D;
	uniform vec3 u_size;
	uniform int u_mip;
	uniform float u_step;
	uniform sampler3D u_data;
	uniform sampler2D u_lut;
	uniform sampler3D u_bricks;
	uniform vec3 u_brickScale;
	uniform sampler2D u_depth;
	uniform bool u_useDepth;
	uniform mat4 u_objToClip;
	varying vec3 v_position;
	varying vec3 v_cameraInObj;
	varying vec3 v_viewDirInObj;
	varying vec4 v_clip;
	const int MAX_STEPS = 1024;
	const float BRICK = ${BRICK}.0;

	vec4 lut( float v ) { return texture2D( u_lut, vec2( ( v * 255.0 + 0.5 ) / 256.0, 0.5 ) ); }

	// A head light on the local gradient (six samples, only where a sample counts): the
	// relief of bone and vessels, as the surfaces have it.
	float shade( vec3 loc, vec3 ray ) {
		vec3 d = 1.0 / u_size;
		vec3 g = vec3(
			texture( u_data, loc + vec3( d.x, 0, 0 ) ).r - texture( u_data, loc - vec3( d.x, 0, 0 ) ).r,
			texture( u_data, loc + vec3( 0, d.y, 0 ) ).r - texture( u_data, loc - vec3( 0, d.y, 0 ) ).r,
			texture( u_data, loc + vec3( 0, 0, d.z ) ).r - texture( u_data, loc - vec3( 0, 0, d.z ) ).r );
		float m = length( g );
		if ( m < 1e-3 ) return 1.0;
		return 0.45 + 0.55 * abs( dot( g / m, ray ) );
	}

	// Steps (at least one) from loc to past the edge of its brick of BRICK voxels a side.
	int stepsOutOfBrick( vec3 loc, vec3 step ) {
		vec3 b = floor( loc * u_size / BRICK );
		vec3 edge = ( b + vec3( greaterThan( step, vec3( 0.0 ) ) ) ) * BRICK / u_size;
		vec3 t = ( edge - loc ) / mix( step, vec3( 1e-9 ), vec3( lessThan( abs( step ), vec3( 1e-9 ) ) ) );
		t = mix( t, vec3( 1e9 ), vec3( lessThan( abs( step ), vec3( 1e-9 ) ) ) );
		return max( 1, int( ceil( min( min( t.x, t.y ), t.z ) ) ) );
	}

	// Window depth (0..1) of a point in voxel coordinates.
	float depthOf( vec3 p ) {
		vec4 c = u_objToClip * vec4( p, 1.0 );
		return c.z / c.w * 0.5 + 0.5;
	}

	void main() {
		vec3 ray = isOrthographic ? normalize( - v_viewDirInObj ) : normalize( v_cameraInObj - v_position );
		vec3 t1 = ( vec3( - 0.5 ) - v_position ) / ray;
		vec3 t2 = ( u_size - vec3( 0.5 ) - v_position ) / ray;
		vec3 tmax = max( t1, t2 );
		float len = min( min( tmax.x, tmax.y ), tmax.z );
		if ( ! isOrthographic ) len = min( len, length( v_cameraInObj - v_position ) ); // camera inside
		vec3 front = v_position + ray * len;
		vec3 back = v_position;
		if ( u_useDepth ) {
			// The opaque surfaces drawn before: the ray ends where the nearest one is.
			vec2 uv = v_clip.xy / v_clip.w * 0.5 + 0.5;
			float surface = texture2D( u_depth, uv ).r;
			float dFront = depthOf( front );
			float dBack = depthOf( back );
			if ( surface <= dFront ) discard;
			if ( surface < dBack ) back = mix( front, back, clamp( ( surface - dFront ) / ( dBack - dFront ), 0.0, 1.0 ) );
		}
		int nsteps = int( length( back - front ) / u_step + 0.5 );
		if ( nsteps < 1 ) discard;
		vec3 step = ( back - front ) / u_size / float( nsteps );
		vec3 loc = ( front + 0.5 ) / u_size;
		if ( u_mip == 1 ) {
			float best = 0.0;
			for ( int i = 0; i < MAX_STEPS; i ++ ) {
				if ( i >= nsteps ) break;
				best = max( best, texture( u_data, loc ).r );
				loc += step;
			}
			// Alpha is the windowed brightness: air lets the surfaces and the background
			// through, the brightest voxel along the ray covers them.
			vec4 c = lut( best );
			if ( c.r < 0.01 ) discard;
			gl_FragColor = vec4( vec3( 1.0 ), c.r );
			return;
		}
		vec4 sum = vec4( 0.0 );
		int i = 0;
		int brickEnd = 0; // the first step past the brick the ray is in, once looked at
		for ( int n = 0; n < MAX_STEPS; n ++ ) {
			if ( i >= nsteps || sum.a >= 0.95 ) break; // what lies behind hardly shows
			if ( i >= brickEnd ) {
				// A brick this window leaves transparent is stepped over; any other is
				// marched through without looking at it again.
				brickEnd = i + stepsOutOfBrick( loc, step );
				if ( texture( u_bricks, loc * u_brickScale ).r == 0.0 ) {
					loc += step * float( brickEnd - i );
					i = brickEnd;
					continue;
				}
			}
			vec4 c = lut( texture( u_data, loc ).r );
			float a = 1.0 - pow( 1.0 - c.a, u_step ); // the table's opacity is per voxel
			if ( a > 0.004 ) c.rgb *= shade( loc, ray );
			sum.rgb += ( 1.0 - sum.a ) * a * c.rgb;
			sum.a += ( 1.0 - sum.a ) * a;
			loc += step;
			i ++;
		}
		if ( sum.a < 0.01 ) discard;
		gl_FragColor = vec4( sum.rgb / sum.a, sum.a );
	}`;

export class VolumeLayer {
	// header, data: the decoded /voxels body; lpsToWorld: the viewer's matrix.
	constructor( header, data, lpsToWorld ) {
		this.header = header;
		this.data = data; // the voxels, also read by the transfer function's histogram
		this.presets = presetsFor( header );
		const [ nx, ny, nz ] = header.dims;
		const texture = new THREE.Data3DTexture( data, nx, ny, nz );
		texture.format = THREE.RedFormat;
		texture.type = THREE.UnsignedByteType;
		texture.minFilter = texture.magFilter = THREE.LinearFilter;
		texture.unpackAlignment = 1;
		texture.needsUpdate = true;
		this.lut = new THREE.DataTexture( new Uint8Array( 256 * 4 ), 256, 1 );
		this.lut.minFilter = this.lut.magFilter = THREE.LinearFilter;
		this.ranges = brickRanges( data, header.dims );
		const [ bx, by, bz ] = this.ranges.dims;
		this.bricks = new THREE.Data3DTexture( new Uint8Array( bx * by * bz ), bx, by, bz );
		this.bricks.format = THREE.RedFormat;
		this.bricks.unpackAlignment = 1;
		// A version of what is drawn other than the camera (the window, the preset): a
		// change is drawn fast first, as a turn is.
		this.version = 0;
		const geometry = new THREE.BoxGeometry( nx, ny, nz ).translate( ( nx - 1 ) / 2, ( ny - 1 ) / 2, ( nz - 1 ) / 2 );
		this.material = new THREE.ShaderMaterial( {
			uniforms: {
				u_size: { value: new THREE.Vector3( nx, ny, nz ) },
				u_mip: { value: 0 },
				// One voxel a step: the first level is at most 256 a side, so a ray takes at
				// most ~450 samples, fewer where it is opaque (half a voxel doubled a frame's
				// time in software WebGL for little to see).
				u_step: { value: 1.0 },
				u_data: { value: texture },
				u_lut: { value: this.lut },
				u_bricks: { value: this.bricks },
				// Texture coordinates -> the brick texture's (the last brick may be partial).
				u_brickScale: { value: new THREE.Vector3( nx / ( BRICK * bx ), ny / ( BRICK * by ), nz / ( BRICK * bz ) ) },
				u_depth: { value: null },
				u_useDepth: { value: false },
				u_objToClip: { value: new THREE.Matrix4() },
			},
			vertexShader, fragmentShader,
			side: THREE.BackSide, transparent: true, depthTest: false, depthWrite: false,
		} );
		this.mesh = new THREE.Mesh( geometry, this.material );
		this.mesh.name = 'volume';
		this.mesh.renderOrder = 10; // after the opaque surfaces
		this.mesh.matrixAutoUpdate = false;
		this.mesh.frustumCulled = false;
		this.place( lpsToWorld );
		const name = Object.keys( this.presets )[ 0 ];
		this.setPreset( name );
	}

	// Voxel -> LPS mm (the header's affine, row-major) -> the viewer's world.
	place( lpsToWorld ) {
		const affine = new THREE.Matrix4().set( ...this.header.affine.flat() );
		this.mesh.matrix.copy( lpsToWorld ).multiply( affine );
		this.mesh.matrixWorldNeedsUpdate = true;
	}

	setPreset( name ) {
		this.preset = name;
		const p = this.presets[ name ];
		this.setWindow( p.level, p.window );
	}

	// Centre and width in the volume's units (HU for CT).
	setWindow( level, width ) {
		const p = this.presets[ this.preset ];
		Object.assign( this, { level, width } );
		const table = lookupTable( this.header, p, level, width );
		this.lut.image.data.set( table );
		this.lut.needsUpdate = true;
		this.bricks.image.data.set( occupancy( this.ranges, table, p.mip ) );
		this.bricks.needsUpdate = true;
		this.material.uniforms.u_mip.value = p.mip ? 1 : 0;
		this.version ++;
	}

	// Voxels a ray step (1: every voxel; more while the camera moves).
	setStep( voxels ) {
		this.material.uniforms.u_step.value = voxels;
	}

	// The opaque surfaces' depth (a DepthTexture of the frame's size), or null.
	setDepth( texture, camera ) {
		const u = this.material.uniforms;
		u.u_depth.value = texture;
		u.u_useDepth.value = !! texture;
		this.mesh.updateMatrixWorld();
		u.u_objToClip.value.multiplyMatrices( camera.projectionMatrix, camera.matrixWorldInverse ).multiply( this.mesh.matrixWorld );
	}

	dispose() {
		this.mesh.geometry.dispose();
		this.material.dispose();
		this.material.uniforms.u_data.value.dispose();
		this.lut.dispose();
		this.bricks.dispose();
	}
}
