// One orthogonal slice view: a server-rendered PNG (window/level applied, the
// voxels above the threshold tinted, a label map's colours laid over), fitted to
// its box at the physical aspect ratio the server already gives it. The pointer
// tools (readout, cross-hair, zoom, window/level) are in slice-tools.js.

import { urls } from './api.js';
import { el } from './format.js';
import { SliceTools } from './slice-tools.js';

// Screen edges in patient terms as the server draws the views (radiological
// convention: the patient's right on the screen's left, superior up).
const ORIENT = {
	axial: { top: 'A', bottom: 'P', left: 'R', right: 'L' },
	coronal: { top: 'S', bottom: 'I', left: 'R', right: 'L' },
	sagittal: { top: 'S', bottom: 'I', left: 'A', right: 'P' },
};

export class SliceView {
	// root: the .view article; count: slices along this axis; view: the volume's
	// views[axis] (which voxel axes run across and down, flipped or not); dims: the
	// volume's; tools: SliceTools' callbacks (onHover, onPick, onWindowLevel).
	constructor( root, { volumeId, axis, count, index, display, onIndex = () => {}, view = null, dims = null, tools = {} } ) {
		this.root = root;
		this.volumeId = volumeId;
		this.axis = axis;
		this.count = count;
		this.index = index;
		this.display = display;
		this.onIndex = onIndex;
		this.img = root.querySelector( 'img' );
		this.frame = root.querySelector( '.frame' );
		this.stage = root.querySelector( '.stage' );
		this.slider = root.querySelector( 'input[type=range]' );
		this.readout = root.querySelector( '.index' );
		this.wanted = null; // URL the controls ask for
		this.loading = null; // URL in flight; at most one per view so drags never pile up requests
		this.timer = 0;

		for ( const [ side, letter ] of Object.entries( ORIENT[ axis ] || {} ) ) {
			this.stage.append( el( `span.orient.${side}`, { 'aria-hidden': 'true' }, letter ) );
		}
		this.slider.max = String( count - 1 );
		this.slider.value = String( index );
		this.slider.addEventListener( 'input', () => this.setIndex( Number( this.slider.value ) ) );
		// The wheel steps one slice, like a radiology workstation (Ctrl+wheel and a
		// trackpad's pinch, which the browser sends as one, zoom: SliceTools).
		this.stage.addEventListener( 'wheel', ( e ) => {
			if ( e.ctrlKey ) return;
			e.preventDefault();
			this.setIndex( this.index + Math.sign( e.deltaY ) );
		}, { passive: false } );
		this.tools = view && dims ? new SliceTools( this, view, dims, tools ) : null;
		new ResizeObserver( () => this.fit() ).observe( this.stage );
		this.showReadout();
		this.load( 0 );
	}

	setIndex( index ) {
		index = Math.max( 0, Math.min( this.count - 1, Math.round( index ) ) );
		if ( index === this.index ) return;
		this.index = index;
		this.slider.value = String( index );
		this.showReadout();
		this.onIndex( index, this );
		this.load( 40 );
	}

	// display: {window, level, threshold}; delay debounces rapid changes such as a threshold drag.
	setDisplay( display, delay = 150 ) {
		this.display = display;
		this.load( delay );
	}

	showReadout() {
		this.readout.textContent = `${this.index + 1} / ${this.count}`;
	}

	load( delay ) {
		this.wanted = urls.slice( this.volumeId, this.axis, this.index, this.display );
		clearTimeout( this.timer );
		this.timer = setTimeout( () => this.pump(), delay );
	}

	// Loads off-screen and swaps only when decoded, so the picture never blanks;
	// when the wanted URL changed meanwhile, the newest one is fetched next.
	pump() {
		if ( this.loading || this.wanted === this.img.dataset.loaded ) return;
		const url = this.wanted;
		this.loading = url;
		const next = new Image();
		next.onload = () => {
			this.img.src = url;
			this.img.dataset.loaded = url;
			this.natural = [ next.naturalWidth, next.naturalHeight ];
			this.fit();
			this.loading = null;
			this.root.dispatchEvent( new CustomEvent( 'slice-loaded', { detail: { url } } ) );
			this.pump();
		};
		next.onerror = () => {
			this.loading = null;
			this.root.dataset.error = url;
			if ( this.wanted !== url ) this.pump();
		};
		next.src = url;
	}

	// Contain-fit done by hand (not object-fit) so overlays such as the slice
	// range lines can be placed in the image's own coordinates.
	fit() {
		if ( ! this.natural ) return;
		const [ w, h ] = this.natural;
		const box = this.stage.getBoundingClientRect();
		if ( ! box.width || ! box.height ) return;
		const scale = Math.min( box.width / w, box.height / h );
		this.frame.style.width = `${Math.floor( w * scale )}px`;
		this.frame.style.height = `${Math.floor( h * scale )}px`;
	}
}
