// The pointer tools of a consultation: Turn (the orbit controls alone), Laser
// (hovering shows everyone where you point), Pin (click the surface, write a
// note) and Measure (click two surface points). Points are ray-picked on the
// mesh and sent in patient LPS millimetres.

import { onClick } from '../format.js';

export class PointerTools {
	constructor( consultation ) {
		this.c = consultation;
		this.tool = 'orbit';
		this.pendingPin = null;
		this.measureStart = null;
		this.bindCanvas();
	}

	setTool( tool ) {
		this.tool = tool;
		this.c.viewer.annotating = tool === 'pin' || tool === 'measure'; // clicks place, not select
		this.pendingPin = null;
		this.measureStart = null;
		this.c.annotations.mark( null );
		this.c.panel.askPinNote( false );
		this.c.panel.setTool( tool );
		if ( tool !== 'laser' ) this.c.room.send( { type: 'laser', point: null } );
	}

	placePin( note ) {
		if ( ! this.pendingPin ) return;
		this.c.room.send( { type: 'pin', model: this.c.modelId, point: this.pendingPin, note } );
		this.pendingPin = null;
		this.c.annotations.mark( null );
		this.c.panel.askPinNote( false );
	}

	// Clicks (not drags) place pins and measurement ends; hovering moves the laser.
	bindCanvas() {
		const canvas = this.c.viewer.renderer.domElement;
		onClick( canvas, ( e ) => this.click( e.clientX, e.clientY ) );
		canvas.addEventListener( 'pointermove', ( e ) => {
			if ( this.tool !== 'laser' || ! this.c.state.you ) return;
			const hit = this.c.viewer.pick( e.clientX, e.clientY );
			this.c.annotations.laser( this.c.state.you.id, this.c.state.you.colour, hit ? hit.lps : null );
			this.c.room.throttled( 'laser', { type: 'laser', model: this.c.modelId, point: hit ? hit.lps : null }, 60 );
		} );
		canvas.addEventListener( 'pointerleave', () => {
			if ( this.tool === 'laser' ) this.c.room.throttled( 'laser', { type: 'laser', point: null }, 60 );
		} );
	}

	click( x, y ) {
		const tool = this.tool;
		if ( tool !== 'pin' && tool !== 'measure' ) return;
		const hit = this.c.viewer.pick( x, y, { prefer: this.c.viewer.selected } );
		if ( ! hit ) return this.c.panel.showError( 'Nothing there: click on the model itself.' );
		this.c.panel.showError( '' );
		const colour = this.c.state.you?.colour || '#ffffff';
		if ( tool === 'pin' ) {
			this.pendingPin = hit.lps;
			this.c.annotations.mark( hit.lps, colour );
			this.c.panel.askPinNote( true );
		} else if ( ! this.measureStart ) {
			this.measureStart = hit.lps;
			this.c.annotations.mark( hit.lps, colour );
		} else {
			this.c.room.send( { type: 'measure', model: this.c.modelId, a: this.measureStart, b: hit.lps } );
			this.measureStart = null;
			this.c.annotations.mark( null );
		}
	}
}
