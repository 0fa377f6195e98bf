// Start and end slice as two draggable horizontal lines over the sagittal
// view (the 1998 form asked for the numbers; here one can see them). The
// slice axis runs vertically in that picture, superior (the last slice of a
// feet-to-head series) at the top.

import { el } from './format.js';

export class SliceRange {
	// frame: the positioned box around the sagittal image; count: slices on the slice axis.
	constructor( frame, { count, start, end, topIsLast = true, onChange = () => {} } ) {
		this.count = count;
		this.topIsLast = topIsLast;
		this.onChange = onChange;
		this.start = start;
		this.end = end;
		this.shadeTop = el( 'div.range-shade', { style: 'top:0' } );
		this.shadeBottom = el( 'div.range-shade', { style: 'bottom:0' } );
		this.lines = {
			start: this.line( 'start', 'start' ),
			end: this.line( 'end', 'end' ),
		};
		frame.append( this.shadeTop, this.shadeBottom, this.lines.start, this.lines.end );
		this.frame = frame;
		this.draw();
	}

	line( which, label ) {
		const node = el( `div.range-line.${which}`, {
			role: 'slider', tabindex: 0, 'aria-label': `${label} slice`, dataset: { which },
		}, el( 'span', {}, label ) );
		node.addEventListener( 'pointerdown', ( e ) => {
			e.preventDefault();
			node.setPointerCapture( e.pointerId );
			const move = ( ev ) => this.dragTo( which, ev.clientY );
			const up = () => {
				node.removeEventListener( 'pointermove', move );
				node.removeEventListener( 'pointerup', up );
				node.removeEventListener( 'pointercancel', up );
			};
			node.addEventListener( 'pointermove', move );
			node.addEventListener( 'pointerup', up );
			node.addEventListener( 'pointercancel', up );
		} );
		node.addEventListener( 'keydown', ( e ) => {
			const step = { ArrowUp: 1, ArrowDown: - 1, PageUp: 10, PageDown: - 10 }[ e.key ];
			if ( ! step ) return;
			e.preventDefault();
			this.set( which, this[ which ] + ( this.topIsLast ? step : - step ), true );
		} );
		return node;
	}

	// Fraction from the top of the picture for the centre of 1-based slice s.
	fraction( s ) {
		const f = ( s - 0.5 ) / this.count;
		return this.topIsLast ? 1 - f : f;
	}

	sliceAt( clientY ) {
		const box = this.frame.getBoundingClientRect();
		const f = ( clientY - box.top ) / box.height;
		const fromFirst = this.topIsLast ? 1 - f : f;
		return Math.round( fromFirst * this.count + 0.5 );
	}

	dragTo( which, clientY ) {
		this.set( which, this.sliceAt( clientY ), true );
	}

	// Keeps 1 <= start <= end <= count; dragging one line past the other stops at it.
	set( which, value, notify = false ) {
		value = Math.max( 1, Math.min( this.count, Math.round( value ) ) );
		if ( which === 'start' ) value = Math.min( value, this.end );
		else value = Math.max( value, this.start );
		if ( value === this[ which ] ) return;
		this[ which ] = value;
		this.draw();
		if ( notify ) this.onChange( this.start, this.end );
	}

	setRange( start, end ) {
		this.start = Math.max( 1, Math.min( start, end, this.count ) );
		this.end = Math.min( this.count, Math.max( start, end, 1 ) );
		this.draw();
	}

	draw() {
		const pct = ( s ) => `${( this.fraction( s ) * 100 ).toFixed( 3 )}%`;
		this.lines.start.style.top = pct( this.start );
		this.lines.end.style.top = pct( this.end );
		this.lines.start.setAttribute( 'aria-valuenow', this.start );
		this.lines.end.setAttribute( 'aria-valuenow', this.end );
		this.lines.start.querySelector( 'span' ).textContent = `start ${this.start}`;
		this.lines.end.querySelector( 'span' ).textContent = `end ${this.end}`;
		// Shade what will be cut away: above the top line and below the bottom one.
		const top = this.topIsLast ? this.end : this.start;
		const bottom = this.topIsLast ? this.start : this.end;
		const edge = 0.5 / this.count;
		this.shadeTop.style.height = `${Math.max( 0, this.fraction( top ) - edge ) * 100}%`;
		this.shadeBottom.style.height = `${Math.max( 0, 1 - this.fraction( bottom ) - edge ) * 100}%`;
	}
}
