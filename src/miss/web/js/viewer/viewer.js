// The 3-D viewer: a three.js scene that draws only when the view changes
// (OrbitControls 'change', a resize, a new model), never in a busy loop.
// Positions shared with other people (pins, pointers, cameras) are patient LPS
// millimetres: toLps/toWorld convert with the GLB root's matrix and its inverse.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { OrientationGizmo } from './gizmo.js';
import { TiledModel } from './tiles.js';
import { outwardClosed } from './closed.js';
import { VolumePass, whenFinished } from './volume-pass.js';
import { status } from '../test-hooks.js';

// Patient LPS millimetres to glTF's Y-up metres: Left -> +X, Superior -> +Y,
// Anterior (-Y in LPS) -> +Z. Used for the VRML file, which is raw LPS mm,
// until a GLB has told us the server's actual matrix.
const LPS_TO_GLTF = new THREE.Matrix4().set(
	0.001, 0, 0, 0,
	0, 0, 0.001, 0,
	0, - 0.001, 0, 0,
	0, 0, 0, 1 );

export const BACKGROUNDS = { dark: '#1b2128', light: '#f3f5f7' };

// A bone-ivory surface, both sides lit where its inside can show (the clipping plane, an
// open surface): updateSides draws a closed one's front faces only.
function boneMaterial() {
	return new THREE.MeshStandardMaterial( { color: 0xe9dfc8, roughness: 0.6, metalness: 0, side: THREE.DoubleSide } );
}

// A part's own glTF material as the viewer draws it: its colour and opacity,
// both sides lit, translucent parts blended without hiding what lies behind.
function partMaterial( source ) {
	const opacity = source?.opacity ?? 1;
	return new THREE.MeshStandardMaterial( {
		color: source?.color ? source.color.clone() : new THREE.Color( 0xe9dfc8 ),
		roughness: 0.6, metalness: 0, side: THREE.DoubleSide,
		opacity, transparent: opacity < 1, depthWrite: opacity >= 1,
	} );
}

// A MISS-written VRML file's parts, read by vrml-worker.js off this thread (the page stays
// responsive through a file of 100 MB); null when the file is not as MISS writes them.
function readInWorker( url, onProgress ) {
	return new Promise( ( resolve, reject ) => {
		const worker = new Worker( new URL( './vrml-worker.js', import.meta.url ), { type: 'module' } );
		worker.onmessage = ( { data } ) => {
			if ( data.progress ) return onProgress?.( { loaded: data.progress[ 0 ], total: data.progress[ 1 ], lengthComputable: data.progress[ 1 ] > 0 } );
			worker.terminate();
			if ( data.error ) reject( new Error( data.error ) );
			else resolve( data.unknown ? null : data.parts );
		};
		worker.onerror = ( e ) => {
			worker.terminate();
			reject( new Error( e.message || 'the VRML reader failed' ) );
		};
		worker.postMessage( { url: new URL( url, location.href ).href } );
	} );
}

// One part read by the worker as a mesh in LPS mm, coloured as its Material says (sRGB).
function vrmlMesh( p ) {
	const geometry = new THREE.BufferGeometry();
	geometry.setAttribute( 'position', new THREE.BufferAttribute( p.positions, 3 ) );
	if ( p.normals ) geometry.setAttribute( 'normal', new THREE.BufferAttribute( p.normals, 3 ) );
	geometry.setIndex( new THREE.BufferAttribute( p.indices, 1 ) );
	const material = new THREE.MeshPhongMaterial( { color: new THREE.Color().setRGB( ...p.color, THREE.SRGBColorSpace ), opacity: p.opacity, transparent: p.opacity < 1 } );
	const mesh = new THREE.Mesh( geometry, material );
	mesh.name = p.name;
	return mesh;
}

export function countTriangles( object ) {
	let n = 0;
	object.traverse( ( o ) => {
		if ( ! o.isMesh ) return;
		const g = o.geometry;
		n += ( g.index ? g.index.count : g.attributes.position.count ) / 3;
	} );
	return Math.round( n );
}

// WebGL drawn in software (no GPU, or one the browser will not use: SwiftShader,
// llvmpipe; many hospital desktops and virtual machines) pays for multisampling on every
// pixel of every frame: there a frame of CThead's 144 k-triangle skull at 1366 x 768
// took 0.8 s with it and 0.4 s without (headless chromium, 2 cores). There the viewer
// draws without it; on a GPU, with it.
function softwareWebGL() {
	try {
		const gl = document.createElement( 'canvas' ).getContext( 'webgl2' );
		if ( ! gl ) return false;
		const info = gl.getExtension( 'WEBGL_debug_renderer_info' );
		const name = String( gl.getParameter( info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER ) );
		gl.getExtension( 'WEBGL_lose_context' )?.loseContext();
		return /swiftshader|llvmpipe|softpipe|software|basic render/i.test( name );
	} catch {
		return false;
	}
}

export class ModelViewer {
	constructor( container ) {
		this.container = container;
		const software = softwareWebGL();
		Object.assign( status, { softwareWebGL: software, antialias: ! software } );
		this.renderer = new THREE.WebGLRenderer( { antialias: ! software } );
		this.renderer.setPixelRatio( Math.min( window.devicePixelRatio, 2 ) );
		this.renderer.autoClear = false;
		this.renderer.localClippingEnabled = true;
		container.prepend( this.renderer.domElement );
		this.bindKeys( this.renderer.domElement );

		this.scene = new THREE.Scene();
		this.camera = new THREE.PerspectiveCamera( 30, 1, 0.001, 100 );
		this.camera.position.set( 0, 0, 1 ); // glTF front (anterior) until a model is framed
		this.scene.add( this.camera );
		this.addLights();
		this.material = boneMaterial();
		this.lpsToWorld = LPS_TO_GLTF.clone();
		this.gizmo = new OrientationGizmo();
		this.gizmo.setFrame( this.lpsToWorld );
		this.model = null;
		// A large model's levels of detail (TiledModel) when it is drawn from them.
		this.tiles = null;
		// A scene's named parts ({name, mesh, material, extras}); one entry for a plain surface.
		this.parts = [];
		// Called once after the next render (whenDrawn).
		this.afterRender = [];
		this.selected = null;
		// The clipping plane (world space), shared by every part's material; off until set.
		this.clipPlane = new THREE.Plane( new THREE.Vector3( 0, - 1, 0 ), 0 );
		this.clipping = null;
		this.background = 'dark';
		// Annotations (pins, pointers, measurements) live here, apart from the model.
		this.overlay = new THREE.Group();
		this.overlay.name = 'annotations';
		this.scene.add( this.overlay );
		this.changeListeners = [];
		this.raycaster = new THREE.Raycaster();
		this.makeControls();
		this.pending = false;
		new ResizeObserver( () => this.resize() ).observe( container );
		this.resize();
	}

	// Sky light from the patient's head, a key light riding on the camera so
	// the side facing the viewer is always lit, whichever way it is turned.
	addLights() {
		this.hemi = new THREE.HemisphereLight( 0xf4f7ff, 0x3a3228, 0.9 );
		this.scene.add( this.hemi );
		// Up and to the left of the viewer, like a desk lamp: relief shows without harsh shadows.
		const key = new THREE.DirectionalLight( 0xffffff, 2.6 );
		key.position.set( - 0.9, 1.0, 0.7 );
		this.camera.add( key, key.target );
	}

	// OrbitControls fixes its "up" when built, so it is rebuilt when the
	// patient's superior direction (the camera's up) changes.
	makeControls() {
		this.controls?.dispose();
		const enabled = this.controls ? this.controls.enabled : true;
		this.controls = new OrbitControls( this.camera, this.renderer.domElement );
		this.controls.enabled = enabled;
		this.controls.addEventListener( 'change', () => {
			this.requestRender();
			for ( const fn of this.changeListeners ) fn();
		} );
	}

	// The 3-D view from the keyboard: it takes focus (Tab) and names itself; arrow keys turn
	// the model about its target (15° a press), + and − zoom, Home fits it in view.
	bindKeys( canvas ) {
		canvas.tabIndex = 0;
		canvas.setAttribute( 'role', 'application' );
		canvas.setAttribute( 'aria-roledescription', '3-D view' );
		canvas.setAttribute( 'aria-label', 'The model in 3-D: drag or use the arrow keys to turn it, + and − to zoom, Home to fit it in view' );
		const STEP = Math.PI / 12;
		canvas.addEventListener( 'keydown', ( e ) => {
			if ( ! this.controls.enabled || e.altKey || e.ctrlKey || e.metaKey ) return;
			const turns = { ArrowLeft: [ STEP, 0 ], ArrowRight: [ - STEP, 0 ], ArrowUp: [ 0, STEP ], ArrowDown: [ 0, - STEP ] };
			const zooms = { '+': 0.8, '=': 0.8, '-': 1.25, '_': 1.25 };
			if ( turns[ e.key ] ) this.turnBy( ...turns[ e.key ] );
			else if ( zooms[ e.key ] ) this.zoomBy( zooms[ e.key ] );
			else if ( e.key === 'Home' ) this.fit();
			else return;
			e.preventDefault();
			for ( const fn of this.changeListeners ) fn(); // as a drag: a presenter's view is sent
		} );
	}

	// Turns the camera about the controls' target as a drag does: `across` about the up
	// direction, `over` towards or away from it (stopping short of the poles, as the orbit
	// controls do, so up stays up).
	turnBy( across, over ) {
		const target = this.controls.target;
		const up = this.camera.up;
		const offset = this.camera.position.clone().sub( target ).applyAxisAngle( up, across );
		const right = new THREE.Vector3().crossVectors( up, offset ).normalize();
		const tilted = offset.clone().applyAxisAngle( right, - over );
		const pole = tilted.angleTo( up );
		if ( pole > 0.05 && pole < Math.PI - 0.05 ) offset.copy( tilted );
		this.setWorldPose( target.clone().add( offset ), target, up );
	}

	zoomBy( factor ) {
		const target = this.controls.target;
		const offset = this.camera.position.clone().sub( target ).multiplyScalar( factor );
		this.setWorldPose( target.clone().add( offset ), target, this.camera.up );
	}

	// fn() after every camera change made by the user's orbit controls.
	onCameraChange( fn ) {
		this.changeListeners.push( fn );
	}

	toLps( world ) {
		const inverse = this.lpsToWorld.clone().invert();
		const p = world.clone().applyMatrix4( inverse );
		return [ p.x, p.y, p.z ];
	}

	toWorld( lps ) {
		return new THREE.Vector3( ...lps ).applyMatrix4( this.lpsToWorld );
	}

	// A direction in LPS (the camera's up) as a unit vector in world space.
	lpsDirectionToWorld( lps ) {
		return new THREE.Vector3( ...lps ).transformDirection( this.lpsToWorld );
	}

	// The surface point under a pixel of the canvas: {world, lps} or null. Of the parts
	// drawn there, the first opaque one: a translucent skin lets the click through to the
	// bone it shows, as the eye does (only a pixel with nothing opaque behind lands on the
	// translucent part). `prefer`: a part index the user chose, taken first if hit.
	pick( clientX, clientY, { prefer = null } = {} ) {
		if ( ! this.model ) return null;
		const rect = this.renderer.domElement.getBoundingClientRect();
		const ndc = new THREE.Vector2( ( ( clientX - rect.left ) / rect.width ) * 2 - 1, - ( ( clientY - rect.top ) / rect.height ) * 2 + 1 );
		this.raycaster.setFromCamera( ndc, this.camera );
		const hits = this.raycaster.intersectObject( this.model, true ).filter( ( h ) => this.isShown( h ) );
		const chosen = prefer == null ? null : this.parts[ prefer ];
		const hit = ( chosen && hits.find( ( h ) => this.partOf( h ) === chosen ) )
			|| hits.find( ( h ) => ( h.object.material?.opacity ?? 1 ) >= 0.99 ) || hits[ 0 ];
		return hit ? { world: hit.point.clone(), lps: this.toLps( hit.point ), object: hit.object } : null;
	}

	// The part a ray hit belongs to (tiles share their part's material), or undefined.
	partOf( hit ) {
		return this.parts.find( ( p ) => p.mesh === hit.object || ( this.tiles && p.material === hit.object.material ) );
	}

	// A ray hit on a part that is drawn there: visible, not faded out, not cut away.
	isShown( hit ) {
		let o = hit.object;
		for ( ; o; o = o.parent ) if ( ! o.visible ) return false;
		if ( hit.object.material?.opacity === 0 || hit.object.material?.visible === false ) return false;
		return ! this.clipping || this.clipPlane.distanceToPoint( hit.point ) >= 0;
	}

	// The camera as patient LPS mm: where it is, what it looks at, which way is up.
	pose() {
		const inverse = this.lpsToWorld.clone().invert();
		const up = this.camera.up.clone().transformDirection( inverse );
		return { position: this.toLps( this.camera.position ), target: this.toLps( this.controls.target ), up: [ up.x, up.y, up.z ] };
	}

	// Places the camera at a pose in world units (see follow.js for the smooth way).
	setWorldPose( position, target, up ) {
		this.camera.position.copy( position );
		this.camera.up.copy( up ).normalize();
		this.controls.target.copy( target );
		this.camera.lookAt( target );
		const dist = position.distanceTo( target ) || 1;
		this.camera.near = dist / 100;
		this.camera.far = dist * 10;
		this.camera.updateProjectionMatrix();
		this.requestRender();
	}

	// Radius of the model's bounding sphere in world units (sizes of markers).
	radius() {
		if ( ! this.model ) return 0.1;
		return new THREE.Box3().setFromObject( this.model ).getBoundingSphere( new THREE.Sphere() ).radius || 0.1;
	}

	requestRender() {
		if ( this.pending ) return;
		this.pending = true;
		requestAnimationFrame( () => {
			this.pending = false;
			this.render();
		} );
	}

	render() {
		const r = this.renderer;
		const { width, height } = r.getSize( new THREE.Vector2() );
		r.setViewport( 0, 0, width, height );
		r.setClearColor( BACKGROUNDS[ this.background ] );
		r.clear();
		this.tiles?.update( this.camera, height );
		// The volume with a model only: a deep link's voxels may come first, and the model
		// places (lpsToWorld) and frames them.
		if ( this.volume?.mesh.visible && this.model ) this.renderWithVolume();
		else r.render( this.scene, this.camera );
		// Read before the gizmo's own render resets the counts.
		status.drawnTriangles = r.info.render.triangles;
		// the first frame that drew anything, kept: a test reads it after later frames refined
		if ( this.model && status.drawnTriangles > 0 ) status.firstDrawnTriangles ??= status.drawnTriangles;
		if ( this.tiles ) {
			status.lod = this.tiles.state();
			this.onDrawn?.( status.drawnTriangles );
		}
		// The gizmo from the frame after the first with a model. Its first frame is slow where
		// WebGL runs in software (0.1 s of this page's time, and more of the GPU's: its
		// shaders, its labels' textures): drawn with the empty stage, it held the page before
		// it could hear of the job's preview; drawn with the first model, it held the model.
		if ( this.model ) {
			if ( this.gizmoDue ) this.gizmo.render( r, this.camera );
			else {
				this.gizmoDue = true;
				this.requestRender();
			}
		}
		for ( const then of this.afterRender.splice( 0 ) ) then();
	}

	// The scan's volume (a VolumeLayer of volume.js) drawn with this scene, or none (null).
	// Its mesh stays out of the scene: it is drawn on its own, after the surfaces.
	setVolume( layer ) {
		this.volume?.dispose();
		this.volume = layer;
		layer?.place( this.lpsToWorld );
		this.requestRender();
	}

	// The surfaces and the volume: fast while the camera moves, in full once it stops
	// (volume-pass.js).
	renderWithVolume() {
		this.volumePass ??= new VolumePass( () => this.requestRender() );
		const quality = this.volumePass.render( this.renderer, this.scene, this.camera, this.volume, BACKGROUNDS[ this.background ] );
		status.volumeFrames = ( status.volumeFrames || 0 ) + 1;
		Object.assign( status, { volumeQuality: quality, volumeFastScale: this.volumePass.scale } );
	}

	// Resolves once the GPU has finished the next frame: a fence put after it, looked at
	// every few milliseconds without blocking the page (the pixels are there, not only
	// asked for; a browser without fences resolves once the frame is asked for).
	whenDrawn() {
		return new Promise( ( resolve ) => {
			this.afterRender.push( () => this.fence( resolve ) );
			this.requestRender();
		} );
	}

	// Resolves once the GPU has finished the next frame in full: with the volume shown, the
	// one drawn when the camera has stopped (a fast frame while it moves does not count).
	whenSettled() {
		return new Promise( ( resolve ) => {
			const then = () => {
				if ( this.volume?.mesh.visible && this.volumePass?.quality === 'fast' ) this.afterRender.push( then );
				else this.fence( resolve );
			};
			this.afterRender.push( then );
			this.requestRender();
		} );
	}

	// resolve() once the GPU has finished what has been asked of it so far.
	fence( resolve ) {
		whenFinished( this.renderer, resolve );
	}

	// A coarse look (a running job's preview) is drawn at half the pixels a side: a
	// quarter of the work where WebGL runs in software, as on many hospital desktops.
	// The next render (requested by the caller) uses it.
	setCoarse( coarse ) {
		this.renderer.setPixelRatio( Math.min( window.devicePixelRatio, 2 ) * ( coarse ? 0.5 : 1 ) );
		const { clientWidth: w, clientHeight: h } = this.container;
		if ( w && h ) this.renderer.setSize( w, h, false );
		this.requestRender();
	}

	resize() {
		const { clientWidth: w, clientHeight: h } = this.container;
		if ( ! w || ! h ) return;
		this.renderer.setSize( w, h, false );
		this.camera.aspect = w / h;
		this.camera.updateProjectionMatrix();
		this.render();
	}

	setBackground( name ) {
		this.background = name;
		this.render();
	}

	// mode 'glb', 'vrml' or 'lod' (url: a large model's tileset.json); resolves with the
	// number of triangles drawn. keepView: the camera stays where it is (a preview replaced
	// by its model), else it frames the model.
	async load( url, mode, onProgress, { keepView = false } = {} ) {
		const tiles = mode === 'lod' ? new TiledModel( url, ( u, root ) => this.loadTile( u, root ), () => this.requestRender() ) : null;
		const loaders = { vrml: () => this.loadVRML( url, onProgress ), lod: () => tiles.init() };
		const object = await ( loaders[ mode ] || ( () => this.loadGLB( url, onProgress ) ) )();
		const meshes = [];
		object.traverse( ( o ) => {
			if ( ! o.isMesh ) return;
			if ( ! o.geometry.attributes.normal ) o.geometry.computeVertexNormals();
			meshes.push( o );
		} );
		// A scene (several parts, or measures in the node extras) keeps each part's
		// colour and opacity; a plain surface is drawn in bone ivory as always.
		// A VRML file's parts carry their colours too (its single part's, as the GLB's does).
		const scene = mode === 'vrml' || meshes.length > 1 || meshes.some( ( o ) => o.userData?.volume_ml != null );
		this.parts = meshes.map( ( o, i ) => {
			o.material = scene ? partMaterial( o.material ) : this.material;
			const extras = { ...o.userData };
			// A tile's measures are its own fragment's: the panel takes the model's from its stats.
			if ( tiles ) for ( const key of [ 'volume_ml', 'area_cm2' ] ) delete extras[ key ];
			// A tile is a piece of the surface: open where it meets the others.
			const closed = ! tiles && outwardClosed( o.geometry );
			return { name: o.name || `part ${i + 1}`, mesh: o, material: o.material, extras, closed };
		} );
		for ( const p of this.parts ) p.material.clippingPlanes = this.clipping ? [ this.clipPlane ] : null;
		status.partColours = this.parts.map( ( p ) => '#' + p.material.color.getHexString( THREE.SRGBColorSpace ) );
		this.updateSides();
		this.clear();
		this.model = object;
		this.tiles = tiles;
		tiles?.setFrame( this.lpsToWorld );
		this.scene.add( object );
		this.gizmo.setFrame( this.lpsToWorld );
		this.volume?.place( this.lpsToWorld ); // its voxels may have come before this file
		if ( keepView ) this.requestRender();
		else this.fit();
		return countTriangles( object );
	}

	// frame: take the LPS->glTF matrix from this file (false for a tile after the root).
	async loadGLB( url, onProgress, { frame = true } = {} ) {
		const gltf = await new GLTFLoader().setMeshoptDecoder( MeshoptDecoder ).loadAsync( url, onProgress );
		const root = gltf.scene;
		root.updateMatrixWorld( true );
		// The server puts LPS->glTF (rotation and mm->m scale) on the root node;
		// read it rather than assume it, and reuse it for VRML mode. The mesh's
		// own node may add a dequantisation matrix, so take its parent's.
		let mesh = null;
		root.traverse( ( o ) => {
			if ( o.isMesh && ! mesh ) mesh = o;
		} );
		if ( mesh?.parent && frame ) this.lpsToWorld.copy( mesh.parent.matrixWorld );
		// three sanitises node names ("bone (300 HU)" -> "bone_(300_HU)"); keep the file's own.
		const nodes = gltf.parser.json.nodes || [];
		root.traverse( ( o ) => {
			const index = gltf.parser.associations.get( o )?.nodes;
			if ( ! o.isMesh || index == null || ! nodes[ index ] ) return;
			o.name = nodes[ index ].name ?? o.name;
			Object.assign( o.userData, nodes[ index ].extras || {} );
		} );
		return root;
	}

	// A tile of a tileset. The root (drawn first) is loaded as any GLB; every other
	// tile's parts are drawn with the parts' own materials (the root tile's, which the
	// structures panel changes), so every level looks the same.
	async loadTile( url, isRoot ) {
		if ( isRoot ) return this.loadGLB( url );
		const tile = await this.loadGLB( url, undefined, { frame: false } );
		tile.traverse( ( o ) => {
			if ( ! o.isMesh ) return;
			if ( ! o.geometry.attributes.normal ) o.geometry.computeVertexNormals();
			const part = this.parts.find( ( p ) => p.name === o.name );
			if ( part ) o.material = part.material;
		} );
		return tile;
	}

	async loadVRML( url, onProgress ) {
		const parts = await readInWorker( url, onProgress );
		status.vrmlReader = parts ? 'worker' : 'VRMLLoader';
		if ( parts ) {
			const group = new THREE.Group();
			for ( const p of parts ) group.add( vrmlMesh( p ) );
			group.matrixAutoUpdate = false;
			group.matrix.copy( this.lpsToWorld );
			return group;
		}
		// Not a file as MISS writes them: three.js's loader, on this thread. Asked for only
		// here: the VRML loader and its parser are a tenth of the page's code.
		const { VRMLLoader } = await import( 'three/addons/loaders/VRMLLoader.js' );
		const vrml = await new VRMLLoader().loadAsync( url, onProgress );
		vrml.updateMatrixWorld( true );
		// Keep the geometry only: a Background, Viewpoint or light in the file
		// must not override the viewer's own.
		const group = new THREE.Group();
		const meshes = [];
		vrml.traverse( ( o ) => {
			if ( o.isMesh && o.material?.side !== THREE.BackSide ) meshes.push( o ); // BackSide: the Background sky
		} );
		for ( const m of meshes ) {
			m.removeFromParent();
			m.matrixWorld.decompose( m.position, m.quaternion, m.scale );
			group.add( m );
		}
		group.matrixAutoUpdate = false;
		group.matrix.copy( this.lpsToWorld );
		return group;
	}

	clear() {
		this.tiles?.dispose();
		this.tiles = null;
		if ( ! this.model ) return;
		this.scene.remove( this.model );
		this.model.traverse( ( o ) => {
			o.geometry?.dispose();
			if ( o.material && o.material !== this.material && ! this.parts.some( ( p ) => p.mesh === o ) ) o.material.dispose?.();
		} );
		this.model = null;
		this.selected = null;
	}

	// Which faces each part draws: its front faces only when it bounds a solid, is opaque
	// and is not cut by the clipping plane (then, from anywhere outside the solid, a back
	// face is always behind a front one); both sides otherwise, so that a cut, an open
	// surface or a translucent shell shows its inside. A frame of a closed skull costs
	// about 40 % less in software WebGL.
	updateSides() {
		for ( const p of this.parts ) {
			const side = p.closed && ! this.clipping && p.material.opacity >= 1 ? THREE.FrontSide : THREE.DoubleSide;
			if ( p.material.side === side ) continue;
			p.material.side = side;
			p.material.needsUpdate = true;
		}
		status.sides = this.parts.map( ( p ) => ( p.material.side === THREE.FrontSide ? 'front' : 'double' ) );
	}

	// --- structures: visibility, colour, opacity, selection, clipping ---

	setPartVisible( index, visible ) {
		this.parts[ index ].mesh.visible = visible;
		// Levels of detail: the part's meshes in every tile share its material.
		if ( this.tiles ) this.parts[ index ].material.visible = visible;
		this.requestRender();
	}

	setPartColor( index, css ) {
		const p = this.parts[ index ];
		if ( p.material === this.material ) p.material = p.mesh.material = this.material.clone();
		p.material.color.set( css );
		this.requestRender();
	}

	setPartOpacity( index, opacity ) {
		const p = this.parts[ index ];
		if ( p.material === this.material ) p.material = p.mesh.material = this.material.clone();
		p.material.opacity = opacity;
		p.material.transparent = opacity < 1;
		p.material.depthWrite = opacity >= 1;
		p.material.needsUpdate = true;
		this.updateSides();
		this.requestRender();
	}

	// Highlights one part (index) or none (null): an amber glow on its material.
	select( index ) {
		for ( const [ i, p ] of this.parts.entries() ) {
			if ( p.material.emissive ) p.material.emissive.set( i === index ? 0x7a4a00 : 0x000000 );
		}
		this.selected = index;
		this.requestRender();
	}

	// The index of the part under a canvas pixel, or null.
	pickPart( clientX, clientY ) {
		const hit = this.pick( clientX, clientY );
		if ( ! hit ) return null;
		const i = this.parts.indexOf( this.partOf( { object: hit.object } ) );
		return i < 0 ? null : i;
	}

	// axis 'axial' | 'coronal' | 'sagittal' | null (off); fraction 0..1 of the model's
	// extent along it: what lies beyond (superior, anterior, left) is cut away, 1 cuts nothing.
	setClipping( axis, fraction = 1 ) {
		this.clipping = axis || null;
		if ( axis && this.model ) {
			const lps = { axial: [ 0, 0, 1 ], coronal: [ 0, - 1, 0 ], sagittal: [ 1, 0, 0 ] }[ axis ];
			const normal = new THREE.Vector3( ...lps ).transformDirection( this.lpsToWorld );
			const box = new THREE.Box3().setFromObject( this.model );
			let lo = Infinity;
			let hi = - Infinity;
			for ( let i = 0; i < 8; i ++ ) {
				const c = new THREE.Vector3( i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z );
				lo = Math.min( lo, c.dot( normal ) );
				hi = Math.max( hi, c.dot( normal ) );
			}
			const at = lo + ( hi - lo ) * fraction + ( fraction >= 1 ? 1e-6 : 0 );
			// Keeps points with normal·x <= at (three clips the negative side).
			this.clipPlane.set( normal.clone().negate(), at );
		}
		const planes = this.clipping ? [ this.clipPlane ] : null;
		const materials = new Set( [ this.material, ...this.parts.map( ( p ) => p.material ) ] );
		for ( const m of materials ) {
			m.clippingPlanes = planes;
			m.needsUpdate = true;
		}
		this.updateSides();
		this.requestRender();
	}

	// One part baked to world space (glTF metres) or patient LPS mm, as a new Mesh.
	partMesh( index, frame = 'world' ) {
		const p = this.parts[ index ];
		p.mesh.updateWorldMatrix( true, false );
		const matrix = p.mesh.matrixWorld.clone();
		if ( frame === 'lps' ) matrix.premultiply( this.lpsToWorld.clone().invert() );
		const src = p.mesh.geometry.attributes.position;
		const positions = new Float32Array( src.count * 3 );
		const v = new THREE.Vector3();
		for ( let i = 0; i < src.count; i ++ ) {
			v.fromBufferAttribute( src, i ).applyMatrix4( matrix );
			positions.set( [ v.x, v.y, v.z ], i * 3 );
		}
		const geometry = new THREE.BufferGeometry();
		geometry.setAttribute( 'position', new THREE.BufferAttribute( positions, 3 ) );
		if ( p.mesh.geometry.index ) geometry.setIndex( Array.from( p.mesh.geometry.index.array ) );
		geometry.computeVertexNormals();
		const material = new THREE.MeshStandardMaterial( {
			color: p.material.color, opacity: p.material.opacity, transparent: p.material.transparent,
			roughness: 0.6, metalness: 0, side: THREE.DoubleSide,
		} );
		const mesh = new THREE.Mesh( geometry, material );
		mesh.name = p.name;
		mesh.userData = { ...p.extras };
		return mesh;
	}

	// Frames the whole model, the patient upright (superior up) and facing
	// the viewer (camera on the anterior side). The box is measured in the
	// view's own axes, so a long, flat scan fills the picture as well as a round one.
	fit() {
		if ( ! this.model ) return;
		this.model.updateMatrixWorld( true );
		const box = new THREE.Box3().setFromObject( this.model );
		const center = box.getCenter( new THREE.Vector3() );
		const anterior = new THREE.Vector3( 0, - 1, 0 ).transformDirection( this.lpsToWorld );
		const superior = new THREE.Vector3( 0, 0, 1 ).transformDirection( this.lpsToWorld );
		const right = new THREE.Vector3().crossVectors( superior, anterior ); // the viewer's right
		const half = { right: 0, up: 0, depth: 0 };
		for ( let i = 0; i < 8; i ++ ) {
			const corner = new THREE.Vector3( i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z ).sub( center );
			half.right = Math.max( half.right, Math.abs( corner.dot( right ) ) );
			half.up = Math.max( half.up, Math.abs( corner.dot( superior ) ) );
			half.depth = Math.max( half.depth, Math.abs( corner.dot( anterior ) ) );
		}
		const tanV = Math.tan( THREE.MathUtils.degToRad( this.camera.fov ) / 2 );
		const tanH = tanV * this.camera.aspect;
		const dist = half.depth + Math.max( half.up / tanV, half.right / tanH ) * 1.12;
		const upChanged = ! this.camera.up.equals( superior );
		this.camera.up.copy( superior );
		this.camera.position.copy( center ).addScaledVector( anterior, dist );
		this.camera.near = dist / 100;
		this.camera.far = dist * 10;
		this.camera.updateProjectionMatrix();
		this.hemi.position.copy( superior ); // sky light from above the head
		if ( upChanged ) this.makeControls();
		this.controls.target.copy( center );
		this.controls.update();
		this.render();
	}
}
