// The volume's histogram on a canvas with a draggable threshold line. Counts
// are drawn on a log scale: air and soft tissue outnumber bone a thousand to
// one, and the bone peak is exactly what a user looks for.

const COLORS = { bars: '#9fb3c4', above: '#e8a33d', line: '#c7611f', text: '#5d6b7a', grid: '#e6eaee' };
const PAD = { left: 8, right: 8, top: 10, bottom: 20 };

// Bin edges (counts + 1 values) from whichever the server sends: `edges`, or
// `bins` as edges, or `bins` as centres (then edges lie halfway between).
export function binEdges( data ) {
	const n = data.counts.length;
	for ( const key of [ 'edges', 'bins' ] ) {
		if ( Array.isArray( data[ key ] ) && data[ key ].length === n + 1 ) return data[ key ];
	}
	const c = data.bins;
	const half = n > 1 ? ( c[ 1 ] - c[ 0 ] ) / 2 : 0.5;
	return [ c[ 0 ] - half, ...c.slice( 0, - 1 ).map( ( v, i ) => ( v + c[ i + 1 ] ) / 2 ), c[ n - 1 ] + half ];
}

export class Histogram {
	// data: {edges or bins, counts: (n), units}; onInput while dragging, onChange when let go.
	constructor( canvas, data, { value, onInput = () => {}, onChange = () => {} } ) {
		this.canvas = canvas;
		this.edges = binEdges( data );
		this.counts = data.counts;
		this.units = data.units || '';
		this.min = this.edges[ 0 ];
		this.max = this.edges[ this.edges.length - 1 ];
		this.value = value;
		this.onInput = onInput;
		this.onChange = onChange;
		const peak = Math.max( 1, ...this.counts );
		this.logPeak = Math.log1p( peak );
		this.bindPointer();
		this.bindKeys();
		new ResizeObserver( () => this.draw() ).observe( canvas );
	}

	setValue( value ) {
		this.value = value;
		this.draw();
	}

	// Plot x (CSS px) <-> value, linear across the histogram's range.
	xOf( v ) {
		const w = this.canvas.clientWidth - PAD.left - PAD.right;
		return PAD.left + ( ( v - this.min ) / ( this.max - this.min ) ) * w;
	}

	valueAt( clientX ) {
		const box = this.canvas.getBoundingClientRect();
		const w = box.width - PAD.left - PAD.right;
		const f = Math.max( 0, Math.min( 1, ( clientX - box.left - PAD.left ) / w ) );
		return this.round( this.min + f * ( this.max - this.min ) );
	}

	// Whole units for wide ranges (HU), a few significant digits for MR's arbitrary scales.
	round( v ) {
		const span = this.max - this.min;
		const step = span > 200 ? 1 : Math.pow( 10, Math.floor( Math.log10( span ) ) - 2 );
		return Math.round( v / step ) * step;
	}

	bindPointer() {
		const c = this.canvas;
		c.addEventListener( 'pointerdown', ( e ) => {
			c.setPointerCapture( e.pointerId );
			this.dragging = true;
			this.update( this.valueAt( e.clientX ) );
		} );
		c.addEventListener( 'pointermove', ( e ) => {
			if ( this.dragging ) this.update( this.valueAt( e.clientX ) );
		} );
		const end = () => {
			if ( ! this.dragging ) return;
			this.dragging = false;
			this.onChange( this.value );
		};
		c.addEventListener( 'pointerup', end );
		c.addEventListener( 'pointercancel', end );
	}

	bindKeys() {
		this.canvas.addEventListener( 'keydown', ( e ) => {
			const dir = { ArrowLeft: - 1, ArrowRight: 1 }[ e.key ];
			if ( ! dir ) return;
			e.preventDefault();
			const bin = ( this.max - this.min ) / this.counts.length;
			this.update( this.round( this.value + dir * bin * ( e.shiftKey ? 10 : 1 ) ) );
			this.onChange( this.value );
		} );
	}

	update( value ) {
		if ( value === this.value ) return;
		this.value = value;
		this.draw();
		this.onInput( value );
	}

	draw() {
		const c = this.canvas;
		const dpr = window.devicePixelRatio || 1;
		const w = c.clientWidth;
		const h = c.clientHeight;
		if ( ! w || ! h ) return;
		if ( c.width !== Math.round( w * dpr ) || c.height !== Math.round( h * dpr ) ) {
			c.width = Math.round( w * dpr );
			c.height = Math.round( h * dpr );
		}
		const g = c.getContext( '2d' );
		g.setTransform( dpr, 0, 0, dpr, 0, 0 );
		g.clearRect( 0, 0, w, h );
		this.drawBars( g, h );
		this.drawThreshold( g, w, h );
		this.drawAxis( g, w, h );
	}

	drawBars( g, h ) {
		const plotH = h - PAD.top - PAD.bottom;
		for ( let i = 0; i < this.counts.length; i ++ ) {
			const x0 = this.xOf( this.edges[ i ] );
			const x1 = this.xOf( this.edges[ i + 1 ] );
			const bh = ( Math.log1p( this.counts[ i ] ) / this.logPeak ) * plotH;
			g.fillStyle = this.edges[ i ] >= this.value ? COLORS.above : COLORS.bars;
			g.fillRect( x0, PAD.top + plotH - bh, Math.max( 1, x1 - x0 - 0.5 ), bh );
		}
	}

	drawThreshold( g, w, h ) {
		const x = this.xOf( this.value );
		g.strokeStyle = COLORS.line;
		g.lineWidth = 2;
		g.beginPath();
		g.moveTo( x, PAD.top - 4 );
		g.lineTo( x, h - PAD.bottom );
		g.stroke();
		const label = `${this.value}${this.units ? ' ' + this.units : ''}`;
		g.font = '600 11px system-ui, sans-serif';
		const tw = g.measureText( label ).width;
		const lx = Math.min( w - tw - 4, Math.max( 4, x + 5 ) );
		g.fillStyle = COLORS.line;
		g.fillText( label, lx, PAD.top + 10 );
	}

	drawAxis( g, w, h ) {
		g.fillStyle = COLORS.text;
		g.font = '11px system-ui, sans-serif';
		g.textBaseline = 'alphabetic';
		g.fillText( String( this.round( this.min ) ), PAD.left, h - 5 );
		const right = String( this.round( this.max ) );
		g.fillText( right, w - PAD.right - g.measureText( right ).width, h - 5 );
		if ( this.min < 0 && this.max > 0 ) {
			const x0 = this.xOf( 0 );
			g.strokeStyle = COLORS.grid;
			g.lineWidth = 1;
			g.beginPath();
			g.moveTo( x0, PAD.top );
			g.lineTo( x0, h - PAD.bottom );
			g.stroke();
		}
	}
}
