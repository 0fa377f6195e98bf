// What people leave on the model, drawn in the viewer's overlay group: pins with
// a number, laser pointers (one per participant, fading when idle) and
// distance measurements with their length. Positions come in patient LPS mm and
// are placed through the viewer's LPS -> scene matrix.

import * as THREE from 'three';

const LASER_FADE_MS = 2500;

function textSprite( text, colour ) {
	const canvas = document.createElement( 'canvas' );
	const g = canvas.getContext( '2d' );
	const font = 'bold 40px system-ui, sans-serif';
	g.font = font;
	canvas.width = Math.ceil( g.measureText( text ).width ) + 28;
	canvas.height = 60;
	g.font = font;
	g.fillStyle = 'rgba(255,255,255,0.92)';
	g.strokeStyle = colour;
	g.lineWidth = 6;
	g.beginPath();
	g.roundRect( 3, 3, canvas.width - 6, canvas.height - 6, 14 );
	g.fill();
	g.stroke();
	g.fillStyle = '#1d2733';
	g.textBaseline = 'middle';
	g.fillText( text, 14, canvas.height / 2 + 2 );
	const texture = new THREE.CanvasTexture( canvas );
	texture.colorSpace = THREE.SRGBColorSpace;
	// Drawn over the surface: a label hidden inside the skull helps nobody.
	const sprite = new THREE.Sprite( new THREE.SpriteMaterial( { map: texture, depthTest: false } ) );
	sprite.renderOrder = 10;
	sprite.userData.aspect = canvas.width / canvas.height;
	return sprite;
}

function ball( colour, radius ) {
	const mesh = new THREE.Mesh( new THREE.SphereGeometry( radius, 20, 14 ), new THREE.MeshBasicMaterial( { color: colour, depthTest: false, transparent: true, opacity: 0.95 } ) );
	mesh.renderOrder = 9;
	return mesh;
}

function dispose( object ) {
	object.traverse( ( o ) => {
		o.geometry?.dispose();
		o.material?.map?.dispose();
		o.material?.dispose();
	} );
}

export class Annotations {
	constructor( viewer ) {
		this.viewer = viewer;
		// A group of its own, so a replay can hide the live annotations and show its own.
		this.group = new THREE.Group();
		viewer.overlay.add( this.group );
		this.pins = new Map(); // id -> {item, object}
		this.measurements = new Map();
		this.lasers = new Map(); // participant id -> {object, timer}
		this.pending = null;
	}

	unit() {
		return this.viewer.radius();
	}

	label( text, colour, at, height ) {
		const sprite = textSprite( text, colour );
		sprite.scale.set( height * sprite.userData.aspect, height, 1 );
		sprite.position.copy( at );
		return sprite;
	}

	// A ball on the surface, a stem up to its number: the label never hides the spot.
	makePin( item, number ) {
		const u = this.unit();
		const group = new THREE.Group();
		const at = this.viewer.toWorld( item.point );
		const head = ball( item.colour, u * 0.028 );
		head.position.copy( at );
		const top = at.clone().add( this.viewer.camera.up.clone().multiplyScalar( u * 0.12 ) );
		const stem = new THREE.Line( new THREE.BufferGeometry().setFromPoints( [ at, top ] ), new THREE.LineBasicMaterial( { color: item.colour, depthTest: false } ) );
		stem.renderOrder = 9;
		const tag = this.label( String( number ), item.colour, top.clone().add( this.viewer.camera.up.clone().multiplyScalar( u * 0.03 ) ), u * 0.06 );
		group.add( stem, head, tag );
		return group;
	}

	setPins( items ) {
		for ( const { object } of this.pins.values() ) this.remove( object );
		this.pins.clear();
		items.forEach( ( item ) => this.addPin( item ) );
	}

	addPin( item ) {
		const object = this.makePin( item, this.pins.size + 1 );
		this.pins.set( item.id, { item, object } );
		this.group.add( object );
		this.viewer.requestRender();
	}

	removePin( id ) {
		const found = this.pins.get( id );
		if ( ! found ) return;
		this.pins.delete( id );
		this.setPins( [ ...this.pins.values() ].map( ( p ) => p.item ) ); // renumber
	}

	makeMeasurement( item ) {
		const u = this.unit();
		const a = this.viewer.toWorld( item.a );
		const b = this.viewer.toWorld( item.b );
		const line = new THREE.Line( new THREE.BufferGeometry().setFromPoints( [ a, b ] ), new THREE.LineBasicMaterial( { color: item.colour, depthTest: false } ) );
		line.renderOrder = 9;
		const ends = [ a, b ].map( ( p ) => {
			const end = ball( item.colour, u * 0.018 );
			end.position.copy( p );
			return end;
		} );
		// The length sits just below the line, so the line itself stays in sight.
		const under = this.viewer.camera.up.clone().multiplyScalar( - u * 0.06 );
		const text = this.label( `${item.mm.toFixed( 1 )} mm`, item.colour, a.clone().lerp( b, 0.5 ).add( under ), u * 0.05 );
		const group = new THREE.Group();
		group.add( line, ...ends, text );
		return group;
	}

	setMeasurements( items ) {
		for ( const { object } of this.measurements.values() ) this.remove( object );
		this.measurements.clear();
		items.forEach( ( item ) => this.addMeasurement( item ) );
	}

	addMeasurement( item ) {
		const object = this.makeMeasurement( item );
		this.measurements.set( item.id, { item, object } );
		this.group.add( object );
		this.viewer.requestRender();
	}

	removeMeasurement( id ) {
		const found = this.measurements.get( id );
		if ( ! found ) return;
		this.measurements.delete( id );
		this.remove( found.object );
	}

	// A participant's pointer at an LPS point (null hides it); it fades when idle.
	laser( id, colour, lps ) {
		const old = this.lasers.get( id );
		if ( old ) {
			clearTimeout( old.timer );
			this.remove( old.object );
			this.lasers.delete( id );
		}
		if ( ! lps ) return this.viewer.requestRender();
		const object = ball( colour, this.unit() * 0.03 );
		object.material.opacity = 0.8;
		object.position.copy( this.viewer.toWorld( lps ) );
		this.group.add( object );
		const timer = setTimeout( () => this.laser( id, colour, null ), LASER_FADE_MS );
		this.lasers.set( id, { object, timer } );
		this.viewer.requestRender();
	}

	// A marker for a point being placed (the first end of a measurement, a pin
	// waiting for its note); null clears it.
	mark( lps, colour = '#ffffff' ) {
		if ( this.pending ) this.remove( this.pending );
		this.pending = null;
		if ( lps ) {
			this.pending = ball( colour, this.unit() * 0.022 );
			this.pending.position.copy( this.viewer.toWorld( lps ) );
			this.group.add( this.pending );
		}
		this.viewer.requestRender();
	}

	// After a (re)load the model's scale may differ: rebuild everything.
	refresh() {
		this.setPins( [ ...this.pins.values() ].map( ( p ) => p.item ) );
		this.setMeasurements( [ ...this.measurements.values() ].map( ( m ) => m.item ) );
	}

	remove( object ) {
		this.group.remove( object );
		dispose( object );
		this.viewer.requestRender();
	}
}

// Removes a set of annotations from the scene for good.
export function discard( annotations ) {
	annotations.viewer.overlay.remove( annotations.group );
	dispose( annotations.group );
	annotations.viewer.requestRender();
}
