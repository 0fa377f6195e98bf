// The transfer-function editor of the Volume section: the scan's histogram (log counts of
// each byte's value, in the volume's units) under the opacity curve of the preset shown;
// dragging a point (or the arrow keys on the selected one) moves it, a double-click adds
// one, Delete (or a right-click) removes it, the colour field colours it. An edit makes
// the "Custom" preset: the points in the volume's own units at the current window, so
// that the window/level fields go on stretching it like any other preset.

import { status } from '../test-hooks.js';

export const CUSTOM = 'Custom';
// Most points a curve may have (a room carries them; its server checks the same number).
export const MAX_POINTS = 32;
const GRAB_PX = 9;

// A preset's points in the volume's units at a window (the inverse of lookupTable's stretch).
export function pointsAt( preset, level, width ) {
	const scale = width / Math.max( preset.window, 1e-6 );
	return preset.points.map( ( [ v, ...rest ] ) => [ level + ( v - preset.level ) * scale, ...rest ] );
}

// Counts of each byte value of the voxels (256 bins).
export function histogram( data ) {
	const bins = new Float64Array( 256 );
	for ( let i = 0; i < data.length; i ++ ) bins[ data[ i ] ] ++;
	return bins;
}

const hex = ( p ) => '#' + p.slice( 1, 4 ).map( ( c ) => Math.round( c * 255 ).toString( 16 ).padStart( 2, '0' ) ).join( '' );

export class TransferEditor {
	// panel: the VolumePanel (its layer, drawn() and onChange); canvas, colour, note: elements.
	constructor( panel, { canvas, colour, note } ) {
		Object.assign( this, { panel, canvas, colour, note } );
		this.bins = histogram( panel.layer.data );
		this.selected = null;
		this.dragging = false;
		canvas.addEventListener( 'pointerdown', ( e ) => this.down( e ) );
		canvas.addEventListener( 'pointermove', ( e ) => this.dragging && this.moveTo( this.selected, this.at( e ) ) );
		canvas.addEventListener( 'pointerup', () => ( this.dragging = false ) );
		canvas.addEventListener( 'dblclick', ( e ) => this.add( this.at( e ) ) );
		canvas.addEventListener( 'contextmenu', ( e ) => {
			e.preventDefault();
			this.pick( e );
			this.remove();
		} );
		canvas.addEventListener( 'keydown', ( e ) => this.key( e ) );
		colour.addEventListener( 'input', () => this.recolour( colour.value ) );
		this.draw();
	}

	layer() {
		return this.panel.layer;
	}

	// Another level's voxels (the full resolution): their histogram.
	useVoxels( data ) {
		this.bins = histogram( data );
		this.draw();
	}

	// The volume's units shown across the canvas: byte 0 to byte 255.
	range() {
		const h = this.layer().header;
		return [ h.offset, h.offset + 255 * h.scale ];
	}

	// The points drawn: the preset's at the current window.
	points() {
		const l = this.layer();
		return pointsAt( l.presets[ l.preset ], l.level, l.width );
	}

	toPx( [ v, , , , a ] ) {
		const [ lo, hi ] = this.range();
		const { width, height } = this.canvas;
		return [ ( v - lo ) / ( hi - lo ) * width, ( 1 - a ) * ( height - 8 ) + 4 ];
	}

	// A pointer event's place as [value (volume's units), opacity].
	at( e ) {
		const r = this.canvas.getBoundingClientRect();
		const [ lo, hi ] = this.range();
		const x = ( e.clientX - r.left ) / r.width;
		const y = ( e.clientY - r.top ) / r.height * this.canvas.height;
		const a = 1 - ( y - 4 ) / ( this.canvas.height - 8 );
		return [ lo + x * ( hi - lo ), Math.min( 1, Math.max( 0, a ) ) ];
	}

	pick( e ) {
		const r = this.canvas.getBoundingClientRect();
		const sx = this.canvas.width / r.width;
		const x = ( e.clientX - r.left ) * sx, y = ( e.clientY - r.top ) * sx;
		const near = this.points().map( ( p, i ) => [ Math.hypot( this.toPx( p )[ 0 ] - x, this.toPx( p )[ 1 ] - y ), i ] ).sort( ( a, b ) => a[ 0 ] - b[ 0 ] )[ 0 ];
		this.selected = near && near[ 0 ] <= GRAB_PX * sx ? near[ 1 ] : null;
		this.draw();
		return this.selected;
	}

	down( e ) {
		this.canvas.focus();
		if ( e.button !== 0 || this.pick( e ) == null ) return;
		this.dragging = true;
		this.canvas.setPointerCapture?.( e.pointerId );
	}

	// Makes `points` the Custom preset, shows it, and says so (to a room, through the panel).
	commit( points ) {
		const l = this.layer();
		l.presets[ CUSTOM ] = { level: l.level, window: l.width, points };
		this.panel.useCustom();
		this.draw();
	}

	// Point i to [value, opacity], kept between its neighbours.
	moveTo( i, [ v, a ] ) {
		if ( i == null ) return;
		const pts = this.points();
		const lo = i > 0 ? pts[ i - 1 ][ 0 ] + 1e-3 : - Infinity;
		const hi = i < pts.length - 1 ? pts[ i + 1 ][ 0 ] - 1e-3 : Infinity;
		pts[ i ] = [ Math.min( hi, Math.max( lo, v ) ), ...pts[ i ].slice( 1, 4 ), a ];
		this.commit( pts );
	}

	add( [ v, a ] ) {
		const pts = this.points();
		if ( pts.length >= MAX_POINTS ) return;
		const i = pts.findIndex( ( p ) => p[ 0 ] > v );
		const at = i < 0 ? pts.length : i;
		const near = pts[ Math.min( at, pts.length - 1 ) ];
		pts.splice( at, 0, [ v, ...near.slice( 1, 4 ), a ] );
		this.selected = at;
		this.commit( pts );
	}

	remove() {
		const pts = this.points();
		if ( this.selected == null || pts.length <= 2 ) return;
		pts.splice( this.selected, 1 );
		this.selected = null;
		this.commit( pts );
	}

	recolour( value ) {
		if ( this.selected == null ) return;
		const pts = this.points();
		const rgb = [ 1, 3, 5 ].map( ( k ) => parseInt( value.slice( k, k + 2 ), 16 ) / 255 );
		pts[ this.selected ] = [ pts[ this.selected ][ 0 ], ...rgb, pts[ this.selected ][ 4 ] ];
		this.commit( pts );
	}

	key( e ) {
		const pts = this.points();
		if ( e.key === 'Tab' ) return;
		if ( e.key === 'Delete' || e.key === 'Backspace' ) this.remove();
		else if ( e.key === 'PageDown' || e.key === 'PageUp' ) {
			const step = e.key === 'PageDown' ? 1 : - 1;
			this.selected = ( ( this.selected ?? - step ) + step + pts.length ) % pts.length;
			this.draw();
		} else if ( e.key.startsWith( 'Arrow' ) && this.selected != null ) {
			const [ lo, hi ] = this.range();
			const p = pts[ this.selected ];
			const dv = { ArrowLeft: - 1, ArrowRight: 1 }[ e.key ] || 0;
			const da = { ArrowDown: - 1, ArrowUp: 1 }[ e.key ] || 0;
			this.moveTo( this.selected, [ p[ 0 ] + dv * ( hi - lo ) / 100, Math.min( 1, Math.max( 0, p[ 4 ] + da * 0.02 ) ) ] );
		} else return;
		e.preventDefault();
	}

	draw() {
		const ctx = this.canvas.getContext( '2d' );
		const { width, height } = this.canvas;
		ctx.clearRect( 0, 0, width, height );
		const top = Math.log1p( Math.max( ...this.bins ) );
		ctx.fillStyle = 'rgba(128, 128, 128, 0.45)';
		for ( let b = 0; b < 256; b ++ ) {
			const h = Math.log1p( this.bins[ b ] ) / top * ( height - 8 );
			ctx.fillRect( b / 256 * width, height - 4 - h, width / 256 + 0.5, h );
		}
		const pts = this.points();
		ctx.strokeStyle = '#1d6fb8';
		ctx.lineWidth = 2;
		ctx.beginPath();
		pts.forEach( ( p, i ) => ctx[ i ? 'lineTo' : 'moveTo' ]( ...this.toPx( p ) ) );
		ctx.stroke();
		pts.forEach( ( p, i ) => {
			const [ x, y ] = this.toPx( p );
			ctx.fillStyle = hex( p );
			ctx.strokeStyle = i === this.selected ? '#000' : '#555';
			ctx.lineWidth = i === this.selected ? 3 : 1;
			ctx.beginPath();
			ctx.arc( x, y, i === this.selected ? 7 : 5, 0, 2 * Math.PI );
			ctx.fill();
			ctx.stroke();
		} );
		const sel = this.selected == null ? null : pts[ this.selected ];
		this.colour.disabled = ! sel;
		if ( sel ) this.colour.value = hex( sel );
		const units = this.layer().header.units || '';
		this.note.textContent = sel
			? `Point ${this.selected + 1} of ${pts.length}: ${Math.round( sel[ 0 ] )} ${units}, opacity ${sel[ 4 ].toFixed( 2 )}`
			: `${Math.round( this.range()[ 0 ] )} to ${Math.round( this.range()[ 1 ] )} ${units} left to right, opacity up. Drag a point; double-click to add one; Delete removes the one picked.`;
		status.transfer = { preset: this.layer().preset, points: pts, selected: this.selected, pixels: pts.map( ( p ) => this.toPx( p ) ), range: this.range() };
	}
}
