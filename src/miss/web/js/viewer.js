// The 3-D viewer: a three.js scene that draws only when the view changes
// (OrbitControls 'change', a resize, a new model), never in a busy loop.
// Positions shared with other people (pins, pointers, cameras) are patient LPS
// millimetres: toLps/toWorld convert with the GLB root's matrix and its inverse.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { VRMLLoader } from 'three/addons/loaders/VRMLLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { OrientationGizmo } from './gizmo.js';

// Patient LPS millimetres to glTF's Y-up metres: Left -> +X, Superior -> +Y,
// Anterior (-Y in LPS) -> +Z. Used for the VRML file, which is raw LPS mm,
// until a GLB has told us the server's actual matrix.
const LPS_TO_GLTF = new THREE.Matrix4().set(
	0.001, 0, 0, 0,
	0, 0, 0.001, 0,
	0, - 0.001, 0, 0,
	0, 0, 0, 1 );

export const BACKGROUNDS = { dark: '#1b2128', light: '#f3f5f7' };

// A bone-ivory surface; both sides lit because a cut (start/end slice) opens the skull.
function boneMaterial() {
	return new THREE.MeshStandardMaterial( { color: 0xe9dfc8, roughness: 0.6, metalness: 0, side: THREE.DoubleSide } );
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

export class ModelViewer {
	constructor( container ) {
		this.container = container;
		this.renderer = new THREE.WebGLRenderer( { antialias: true } );
		this.renderer.setPixelRatio( Math.min( window.devicePixelRatio, 2 ) );
		this.renderer.autoClear = false;
		container.prepend( this.renderer.domElement );

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

	// The surface point under a pixel of the canvas: {world, lps} or null.
	pick( clientX, clientY ) {
		if ( ! this.model ) return null;
		const rect = this.renderer.domElement.getBoundingClientRect();
		const ndc = new THREE.Vector2( ( ( clientX - rect.left ) / rect.width ) * 2 - 1, - ( ( clientY - rect.top ) / rect.height ) * 2 + 1 );
		this.raycaster.setFromCamera( ndc, this.camera );
		const hit = this.raycaster.intersectObject( this.model, true )[ 0 ];
		return hit ? { world: hit.point.clone(), lps: this.toLps( hit.point ) } : null;
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
		r.render( this.scene, this.camera );
		this.gizmo.render( r, this.camera );
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

	// mode 'glb' or 'vrml'; resolves with the number of triangles drawn.
	async load( url, mode, onProgress ) {
		const object = mode === 'vrml' ? await this.loadVRML( url, onProgress ) : await this.loadGLB( url, onProgress );
		object.traverse( ( o ) => {
			if ( ! o.isMesh ) return;
			if ( ! o.geometry.attributes.normal ) o.geometry.computeVertexNormals();
			o.material = this.material;
		} );
		this.clear();
		this.model = object;
		this.scene.add( object );
		this.gizmo.setFrame( this.lpsToWorld );
		this.fit();
		return countTriangles( object );
	}

	async loadGLB( url, onProgress ) {
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
		if ( mesh?.parent ) this.lpsToWorld.copy( mesh.parent.matrixWorld );
		return root;
	}

	async loadVRML( url, onProgress ) {
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
		if ( ! this.model ) return;
		this.scene.remove( this.model );
		this.model.traverse( ( o ) => o.geometry?.dispose() );
		this.model = null;
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
