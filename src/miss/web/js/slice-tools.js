// Pointer tools of one slice view: which voxel is under the pointer, a cross-hair
// at the point the views share, zoom and pan, and window/level by dragging. The
// page decides what a voxel means (its value, asked of the server) and links the
// views; this module only turns pointer gestures into voxels and numbers. The hint
// that names the gestures is volume.html's (#slice-hint).

import { el } from './format.js';

const MAX_ZOOM = 16;

// 0-based voxel index along one axis from a fraction of the picture's width or height.
function place( f, n, flipped ) {
	const i = Math.min( n - 1, Math.floor( f * n ) );
	return flipped ? n - 1 - i : i;
}

// Fraction of the picture's width or height at the centre of voxel i.
function fraction( i, n, flipped ) {
	return ( ( flipped ? n - 1 - i : i ) + 0.5 ) / n;
}

export class SliceTools {
	// slice: its SliceView; view: the volume's views[axis]; dims: the volume's [nx, ny, nz].
	constructor( slice, view, dims, { onHover = () => {}, onPick = () => {}, onWindowLevel = () => {} } = {} ) {
		Object.assign( this, { slice, view, dims, onHover, onPick, onWindowLevel } );
		this.zoom = { s: 1, x: 0, y: 0 };
		this.pointers = new Map();
		this.drag = null;
		this.lines = { h: el( 'div.cross.h', { 'aria-hidden': 'true' } ), v: el( 'div.cross.v', { 'aria-hidden': 'true' } ) };
		slice.frame.append( this.lines.h, this.lines.v );
		this.probe = el( 'div.probe', { hidden: true } );
		slice.stage.append( this.probe );
		const stage = slice.stage;
		stage.addEventListener( 'pointerdown', ( e ) => this.down( e ) );
		stage.addEventListener( 'pointermove', ( e ) => this.move( e ) );
		stage.addEventListener( 'pointerup', ( e ) => this.up( e ) );
		stage.addEventListener( 'pointercancel', ( e ) => this.up( e ) );
		// a finger leaves as it lifts: the readout of its tap stays
		stage.addEventListener( 'pointerleave', ( e ) => this.drag || e.pointerType === 'touch' || this.onHover( null, this ) );
		stage.addEventListener( 'contextmenu', ( e ) => e.preventDefault() ); // right-drag is window/level
		stage.addEventListener( 'dblclick', () => this.zoomTo( 1 ) );
		stage.addEventListener( 'wheel', ( e ) => {
			if ( ! e.ctrlKey ) return; // SliceView steps slices
			e.preventDefault();
			this.zoomTo( this.zoom.s * Math.exp( - e.deltaY * 0.01 ), e.clientX, e.clientY );
		}, { passive: false } );
	}

	// [i, j, k] (0-based) of the voxel under a screen point; null off the picture.
	voxelAt( x, y ) {
		const r = this.slice.frame.getBoundingClientRect();
		const fx = ( x - r.left ) / r.width;
		const fy = ( y - r.top ) / r.height;
		if ( ! ( fx >= 0 && fx < 1 && fy >= 0 && fy < 1 ) ) return null;
		const { horizontal: h, vertical: v } = this.view;
		const ijk = [ 0, 0, 0 ];
		ijk[ this.view.axis ] = this.slice.index;
		ijk[ h.axis ] = place( fx, this.dims[ h.axis ], h.flipped );
		ijk[ v.axis ] = place( fy, this.dims[ v.axis ], v.flipped );
		return ijk;
	}

	// The cross-hair through voxel ijk: where the other two views cut this one.
	setCross( ijk ) {
		const { horizontal: h, vertical: v } = this.view;
		this.lines.v.style.left = `${100 * fraction( ijk[ h.axis ], this.dims[ h.axis ], h.flipped )}%`;
		this.lines.h.style.top = `${100 * fraction( ijk[ v.axis ], this.dims[ v.axis ], v.flipped )}%`;
	}

	// Zoom to scale s about a screen point (the picture's point there stays put).
	zoomTo( s, x, y ) {
		s = Math.max( 1, Math.min( MAX_ZOOM, s ) );
		const z = this.zoom;
		if ( s === 1 ) Object.assign( z, { x: 0, y: 0 } );
		else if ( x != null ) {
			const r = this.slice.frame.getBoundingClientRect();
			z.x += ( ( x - r.left ) / z.s ) * ( z.s - s );
			z.y += ( ( y - r.top ) / z.s ) * ( z.s - s );
		}
		z.s = s;
		this.apply();
	}

	apply() {
		const { s, x, y } = this.zoom;
		const frame = this.slice.frame;
		frame.style.transformOrigin = '0 0';
		frame.style.transform = s === 1 ? '' : `translate(${x}px, ${y}px) scale(${s})`;
		frame.style.setProperty( '--zoom', String( s ) ); // keeps the lines one pixel wide
		this.slice.root.dataset.zoom = s.toFixed( 2 );
	}

	down( e ) {
		if ( e.target.closest( '.range-line' ) ) return; // the slice range's own drag
		this.slice.stage.setPointerCapture( e.pointerId );
		this.pointers.set( e.pointerId, [ e.clientX, e.clientY ] );
		if ( this.pointers.size === 2 ) {
			this.drag = { mode: 'pinch', span: this.span(), s: this.zoom.s };
			return;
		}
		const mode = e.button === 2 || e.shiftKey ? 'window' : 'pan';
		this.drag = { mode, x: e.clientX, y: e.clientY, moved: false };
	}

	span() {
		const [ a, b ] = [ ...this.pointers.values() ];
		return { d: Math.hypot( a[ 0 ] - b[ 0 ], a[ 1 ] - b[ 1 ] ) || 1, x: ( a[ 0 ] + b[ 0 ] ) / 2, y: ( a[ 1 ] + b[ 1 ] ) / 2 };
	}

	move( e ) {
		const d = this.drag;
		if ( ! d ) return void this.onHover( this.voxelAt( e.clientX, e.clientY ), this );
		if ( ! this.pointers.has( e.pointerId ) ) return;
		this.pointers.set( e.pointerId, [ e.clientX, e.clientY ] );
		if ( d.mode === 'pinch' ) {
			if ( this.pointers.size < 2 ) return;
			const now = this.span();
			return void this.zoomTo( d.s * now.d / d.span.d, now.x, now.y );
		}
		const dx = e.clientX - d.x;
		const dy = e.clientY - d.y;
		d.moved ||= Math.hypot( dx, dy ) > 3;
		if ( ! d.moved ) return;
		Object.assign( d, { x: e.clientX, y: e.clientY } );
		if ( d.mode === 'window' ) this.onWindowLevel( dx, dy );
		else if ( this.zoom.s > 1 ) {
			this.zoom.x += dx;
			this.zoom.y += dy;
			this.apply();
		}
	}

	up( e ) {
		const d = this.drag;
		this.pointers.delete( e.pointerId );
		if ( d && d.mode === 'pan' && ! d.moved && e.type === 'pointerup' ) {
			const ijk = this.voxelAt( e.clientX, e.clientY );
			if ( ijk ) this.onPick( ijk, this );
		}
		if ( ! this.pointers.size ) this.drag = null;
	}
}
