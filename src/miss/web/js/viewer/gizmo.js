// A small orientation marker in a corner of the viewer: the patient's axes
// labelled R/L, A/P, S/I, turning with the camera, so a physician always
// knows which way the anatomy faces (colours as in 3D Slicer: R red, A green, S blue).

import * as THREE from 'three';

const AXES = [
	// patient LPS direction, label at its +end, label at its -end, colour
	[ [ 1, 0, 0 ], 'L', 'R', '#d9534f' ],
	[ [ 0, 1, 0 ], 'P', 'A', '#4caf50' ],
	[ [ 0, 0, 1 ], 'S', 'I', '#4a90d9' ],
];

function labelSprite( text, color, strong ) {
	const size = 64;
	const canvas = document.createElement( 'canvas' );
	canvas.width = canvas.height = size;
	const g = canvas.getContext( '2d' );
	g.beginPath();
	g.arc( size / 2, size / 2, size / 2 - 2, 0, Math.PI * 2 );
	g.fillStyle = strong ? color : 'rgba(255,255,255,0.9)';
	g.fill();
	g.lineWidth = 3;
	g.strokeStyle = color;
	g.stroke();
	g.fillStyle = strong ? '#fff' : color;
	g.font = 'bold 36px system-ui, sans-serif';
	g.textAlign = 'center';
	g.textBaseline = 'middle';
	g.fillText( text, size / 2, size / 2 + 2 );
	const texture = new THREE.CanvasTexture( canvas );
	texture.colorSpace = THREE.SRGBColorSpace;
	// Depth-tested, so when an axis points at the viewer its near label hides the far one.
	const sprite = new THREE.Sprite( new THREE.SpriteMaterial( { map: texture, alphaTest: 0.5 } ) );
	sprite.scale.setScalar( 0.55 );
	sprite.userData.label = text;
	return sprite;
}

export class OrientationGizmo {
	constructor( size = 110 ) {
		this.size = size;
		this.scene = new THREE.Scene();
		this.camera = new THREE.OrthographicCamera( - 1.6, 1.6, 1.6, - 1.6, 0.1, 10 );
		this.axes = AXES.map( ( [ dir, plus, minus, color ] ) => {
			const line = new THREE.Line(
				new THREE.BufferGeometry().setFromPoints( [ new THREE.Vector3(), new THREE.Vector3() ] ),
				new THREE.LineBasicMaterial( { color } ) );
			const a = labelSprite( plus, color, true );
			const b = labelSprite( minus, color, false );
			this.scene.add( line, a, b );
			return { lps: new THREE.Vector3( ...dir ), line, plus: a, minus: b };
		} );
	}

	// lpsToWorld: the model's matrix from patient LPS millimetres to the scene;
	// only its rotation matters here.
	setFrame( lpsToWorld ) {
		for ( const axis of this.axes ) {
			const d = axis.lps.clone().transformDirection( lpsToWorld );
			axis.line.geometry.setFromPoints( [ d.clone().multiplyScalar( - 0.95 ), d.clone().multiplyScalar( 0.95 ) ] );
			axis.plus.position.copy( d ).multiplyScalar( 1.15 );
			axis.minus.position.copy( d ).multiplyScalar( - 1.15 );
		}
	}

	// Drawn after the main scene into the bottom-left corner, looking in the
	// same direction as the main camera.
	render( renderer, camera ) {
		this.camera.position.set( 0, 0, 4 ).applyQuaternion( camera.quaternion );
		this.camera.quaternion.copy( camera.quaternion );
		this.camera.updateMatrixWorld();
		renderer.clearDepth();
		renderer.setScissorTest( true );
		renderer.setScissor( 8, 8, this.size, this.size );
		renderer.setViewport( 8, 8, this.size, this.size );
		renderer.render( this.scene, this.camera );
		renderer.setScissorTest( false );
	}
}
