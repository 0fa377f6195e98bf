// Levels of detail: a large model's 3D Tiles 1.1 tileset (miss.export.tiles) drawn
// coarse first, the tiles in view refined as the camera comes closer, within a budget
// of triangles drawn; zooming out coarsens again. Refinement is REPLACE: a tile gives
// way to its children once all of them are loaded, so nothing is ever missing.
//
// Why our own few lines rather than NASA's 3d-tiles-renderer: MISS's tilesets are small
// (hundreds of tiles, one box each, no geospatial frames), the tiles are the GLBs the
// viewer already loads, and this keeps the page free of a dependency and its peers.

import * as THREE from 'three';

// A laptop's integrated GPU keeps about this many triangles smooth.
export const TRIANGLE_BUDGET = 1_500_000;
// A tile is refined while its simplification error covers more pixels than this.
export const MAX_SCREEN_ERROR = 1;
// Tiles loaded at once; more wait their turn.
const MAX_LOADS = 6;

export class TiledModel {
	// url: the tileset.json; loadTile(url, isRoot) resolves with a tile's object (the
	// viewer's GLB loader with the parts' materials); onChange() asks for a new frame.
	constructor( url, loadTile, onChange, { budget = TRIANGLE_BUDGET, maxError = MAX_SCREEN_ERROR } = {} ) {
		this.url = new URL( url, location.href );
		this.loadTile = loadTile;
		this.onChange = onChange;
		this.budget = budget;
		this.maxError = maxError;
		this.group = new THREE.Group();
		this.group.name = 'levels of detail';
		this.nodes = [];
		this.loading = 0;
		this.waiting = [];
		this.disposed = false;
		this.shown = new Set();
	}

	// Reads the tileset and loads its root tile; resolves with the group that draws it.
	async init() {
		const response = await fetch( this.url, { credentials: 'same-origin' } );
		if ( ! response.ok ) throw new Error( `the levels of detail could not be read (${response.status})` );
		const tileset = await response.json();
		this.root = this.node( tileset.root, null );
		await this.load( this.root );
		this.show( new Set( [ this.root ] ) );
		return this.group;
	}

	node( tile, parent ) {
		const [ cx, cy, cz, hx, , , , hy, , , , hz ] = tile.boundingVolume.box;
		const node = {
			uri: new URL( tile.content.uri, this.url ).href,
			error: tile.geometricError, // metres: world units (the GLB's root maps mm to m)
			triangles: tile.extras?.triangles ?? 0,
			lps: [ [ cx - hx, cy - hy, cz - hz ], [ cx + hx, cy + hy, cz + hz ] ], // LPS m
			box: null,
			parent,
			object: null,
			pending: null,
		};
		this.nodes.push( node );
		node.children = ( tile.children || [] ).map( ( t ) => this.node( t, node ) );
		return node;
	}

	// The tiles' boxes in world space, once the root GLB has told the viewer its frame.
	setFrame( lpsToWorld ) {
		for ( const n of this.nodes ) {
			n.box = new THREE.Box3();
			for ( let i = 0; i < 8; i ++ ) {
				const c = [ 0, 1, 2 ].map( ( k ) => n.lps[ ( i >> k ) & 1 ][ k ] * 1000 );
				n.box.expandByPoint( new THREE.Vector3( ...c ).applyMatrix4( lpsToWorld ) );
			}
		}
	}

	load( node ) {
		if ( node.object || node.pending ) return node.pending;
		if ( node.retryAt > performance.now() ) return null; // failed lately (e.g. 429): later
		if ( this.loading >= MAX_LOADS && node !== this.root ) {
			if ( ! this.waiting.includes( node ) ) this.waiting.push( node );
			return null;
		}
		this.loading ++;
		node.pending = this.loadTile( node.uri, node === this.root ).then( ( object ) => {
			if ( this.disposed ) return;
			object.visible = false;
			node.object = object;
			this.group.add( object );
		}, ( err ) => {
			// The root is the model: its failure is the load's. Another tile is tried again
			// later, waiting longer each time (the API's rate limit answers 429 in a burst).
			if ( node === this.root ) throw err;
			node.failures = ( node.failures || 0 ) + 1;
			const wait = Math.min( 30_000, 500 * 2 ** node.failures );
			node.retryAt = performance.now() + wait;
			setTimeout( () => this.disposed || this.onChange(), wait );
			console.warn( `tile ${node.uri} not loaded (${err.message || err}); trying again in ${wait / 1000} s` );
		} ).finally( () => {
			this.loading --;
			node.pending = null;
			const next = this.waiting.shift();
			if ( next && ! this.disposed ) this.load( next );
			if ( ! this.disposed ) this.onChange();
		} );
		return node.pending;
	}

	// Pixels the tile's error covers on screen, seen from the camera (0 when out of view).
	screenError( node, camera, frustum, height ) {
		if ( ! node.box || ! frustum.intersectsBox( node.box ) ) return 0;
		const distance = Math.max( node.box.distanceToPoint( camera.position ), 1e-6 );
		return node.error * height / ( 2 * distance * Math.tan( THREE.MathUtils.degToRad( camera.fov ) / 2 ) );
	}

	// Chooses the tiles to draw for this camera, the largest screen errors refined first,
	// within the budget; asks for the tiles it would refine into. Call before each frame.
	update( camera, height ) {
		if ( ! this.root?.object ) return;
		camera.updateMatrixWorld();
		const frustum = new THREE.Frustum().setFromProjectionMatrix(
			new THREE.Matrix4().multiplyMatrices( camera.projectionMatrix, camera.matrixWorldInverse ) );
		const chosen = new Set( [ this.root ] );
		let total = this.root.triangles;
		const queue = [ { node: this.root, error: this.screenError( this.root, camera, frustum, height ) } ];
		while ( queue.length ) {
			queue.sort( ( a, b ) => b.error - a.error );
			const { node, error } = queue.shift();
			if ( ! node.children.length || error <= this.maxError ) continue;
			const cost = node.children.reduce( ( sum, c ) => sum + c.triangles, 0 ) - node.triangles;
			if ( total + cost > this.budget ) continue;
			if ( ! node.children.every( ( c ) => c.object ) ) {
				for ( const c of node.children ) this.load( c );
				continue;
			}
			chosen.delete( node );
			total += cost;
			for ( const c of node.children ) {
				chosen.add( c );
				queue.push( { node: c, error: this.screenError( c, camera, frustum, height ) } );
			}
		}
		this.show( chosen );
		this.triangles = total;
	}

	show( chosen ) {
		for ( const n of this.nodes ) if ( n.object ) n.object.visible = chosen.has( n );
		this.shown = chosen;
		this.evict();
	}

	// Frees tiles far from use when those loaded hold thrice the budget: the deepest
	// hidden ones first (the root always stays).
	evict() {
		let loaded = this.nodes.reduce( ( sum, n ) => sum + ( n.object ? n.triangles : 0 ), 0 );
		if ( loaded <= 3 * this.budget ) return;
		const hidden = this.nodes.filter( ( n ) => n.object && n !== this.root && ! this.shown.has( n ) );
		hidden.sort( ( a, b ) => depth( b ) - depth( a ) );
		for ( const n of hidden ) {
			if ( loaded <= 2 * this.budget ) break;
			this.group.remove( n.object );
			n.object.traverse( ( o ) => o.geometry?.dispose() );
			n.object = null;
			loaded -= n.triangles;
		}
	}

	// What the tests and the statistics read: tiles drawn and loading.
	state() {
		return { tiles: this.shown.size, loading: this.loading + this.waiting.length, triangles: this.triangles ?? this.root?.triangles ?? 0 };
	}

	dispose() {
		this.disposed = true;
		this.waiting = [];
	}
}

function depth( node ) {
	let d = 0;
	for ( let n = node.parent; n; n = n.parent ) d ++;
	return d;
}
