// The viewer's structure list: one row per part of the loaded model with
// visibility, colour and opacity; a click on a part (or its row) selects it and
// shows its name, volume (mL) and surface area (cm²); a clipping plane along an
// axial, coronal or sagittal cut; the selected part downloaded on its own.
// Everything only asks the viewer to draw again (render on demand).

import { el, onClick } from '../format.js';
import { status } from '../test-hooks.js';

const $ = ( id ) => document.getElementById( id );

function hex( color ) {
	return `#${color.getHexString()}`;
}

function fileName( name, ext ) {
	const base = name.normalize( 'NFKD' ).replace( /[^\w.-]+/g, '_' ).replace( /_+/g, '_' ).replace( /^_|_$/g, '' );
	return `${base || 'part'}.${ext}`;
}

function save( data, name, type ) {
	const url = URL.createObjectURL( new Blob( [ data ], { type } ) );
	const a = el( 'a', { href: url, download: name, hidden: true } );
	document.body.append( a );
	a.click();
	a.remove();
	setTimeout( () => URL.revokeObjectURL( url ), 10_000 );
}

export class StructuresPanel {
	// Names and colours come with the model (the server writes what the volume page asked
	// for); stats.parts gives each part's name, volume (mL) and area (cm²).
	// canDownload: may the selected part be saved on its own (a share link may forbid it)?
	constructor( viewer ) {
		this.viewer = viewer;
		this.stats = {};
		this.canDownload = true;
		this.onChange = () => {}; // what shows changed by this person's hand (a room shares it)
		this.bindCanvas();
		$( 'clip-axis' ).addEventListener( 'change', () => this.clip( true ) );
		$( 'clip-position' ).addEventListener( 'input', () => this.clip( true ) );
		for ( const b of document.querySelectorAll( '[data-part-format]' ) ) {
			b.addEventListener( 'click', () => this.download( b.dataset.partFormat ) );
		}
		status.structures = { parts: [], selected: null, clip: null };
	}

	setStats( stats ) {
		this.stats = stats || {};
	}

	// After every load (GLB or VRML): rebuild the list from the viewer's parts.
	refresh() {
		const parts = this.viewer.parts;
		const measured = this.stats.parts || [];
		for ( const [ i, p ] of parts.entries() ) {
			const m = measured[ i ] || {};
			// The VRML loader drops the parts' names: the model's stats list them in the same order.
			if ( parts.length === measured.length && p.extras.volume_ml == null && m.name ) p.name = m.name;
			p.volume_ml = p.extras.volume_ml ?? m.volume_ml;
			p.area_cm2 = p.extras.area_cm2 ?? m.area_cm2;
		}
		$( 'structure-list' ).replaceChildren( ...parts.map( ( p, i ) => this.row( p, i ) ) );
		$( 'structures-section' ).hidden = parts.length === 0;
		this.showSelected( null );
		this.clip();
		this.publish();
	}

	row( part, i ) {
		const visible = el( 'input', { type: 'checkbox', checked: part.mesh.visible, 'aria-label': `Show ${part.name}`, dataset: { role: 'visible' } } );
		visible.addEventListener( 'change', () => {
			this.viewer.setPartVisible( i, visible.checked );
			this.publish();
			this.onChange();
		} );
		const color = el( 'input', { type: 'color', value: hex( part.material.color ), 'aria-label': `Colour of ${part.name}`, dataset: { role: 'color' } } );
		color.addEventListener( 'input', () => {
			this.viewer.setPartColor( i, color.value );
			this.publish();
		} );
		const opacity = el( 'input', {
			type: 'range', min: 0, max: 1, step: 0.05, value: part.material.opacity, 'aria-label': `Opacity of ${part.name}`, dataset: { role: 'opacity' },
		} );
		opacity.addEventListener( 'input', () => {
			this.viewer.setPartOpacity( i, Number( opacity.value ) );
			this.publish();
			this.onChange();
		} );
		// label tables name structures in snake_case: read as words, the full name on hover
		const shown = part.name.replace( /_/g, ' ' );
		const name = el( 'button.link.part-name', { type: 'button', title: `Select ${shown}`, onclick: () => this.showSelected( i ) }, shown );
		return el( 'li.structure-row', { dataset: { index: i } }, visible, color, name, opacity );
	}

	bindCanvas() {
		onClick( this.viewer.renderer.domElement, ( e ) => {
			// a click of the room's Pin or Measure tool places a point; it selects nothing
			if ( this.viewer.parts.length && ! this.viewer.annotating ) this.showSelected( this.viewer.pickPart( e.clientX, e.clientY ) );
		} );
	}

	// What shows, as a room shares it: each part's visibility and opacity, the clipping.
	display() {
		const axis = $( 'clip-axis' ).value;
		return {
			parts: this.viewer.parts.map( ( p ) => ( { visible: p.mesh.visible, opacity: p.material.opacity } ) ),
			clip: axis ? { axis, fraction: Number( $( 'clip-position' ).value ) } : null,
		};
	}

	// Shows what a room says shows (the presenter's or the owner's), without sending it on.
	applyDisplay( state ) {
		if ( ! state ) return;
		for ( const [ i, part ] of ( state.parts || [] ).entries() ) {
			if ( i >= this.viewer.parts.length ) break;
			this.viewer.setPartVisible( i, part.visible );
			this.viewer.setPartOpacity( i, part.opacity );
			const row = $( 'structure-list' ).querySelector( `[data-index="${i}"]` );
			if ( row ) {
				row.querySelector( '[data-role=visible]' ).checked = part.visible;
				row.querySelector( '[data-role=opacity]' ).value = part.opacity;
			}
		}
		$( 'clip-axis' ).value = state.clip ? state.clip.axis : '';
		$( 'clip-position' ).value = state.clip ? state.clip.fraction : 1;
		this.clip();
		this.publish();
	}

	showSelected( index ) {
		this.viewer.select( index );
		for ( const li of $( 'structure-list' ).children ) li.classList.toggle( 'selected', Number( li.dataset.index ) === index );
		const p = index == null ? null : this.viewer.parts[ index ];
		// A large model drawn from its levels of detail holds no part at full resolution in
		// the page: its full-resolution files are under Download.
		$( 'part-download' ).hidden = ! p || ! this.canDownload || Boolean( this.viewer.tiles );
		const info = $( 'part-info' );
		if ( ! p ) {
			info.textContent = 'Click a part to see its name, volume and area.';
		} else {
			const fmt = ( v, unit, digits ) => ( v == null ? '–' : `${Number( v ).toFixed( digits )} ${unit}` );
			info.replaceChildren(
				el( 'strong.part-selected', {}, p.name ),
				el( 'span', {}, ` · volume ${fmt( p.volume_ml, 'mL', 2 )} · area ${fmt( p.area_cm2, 'cm²', 1 )}` ) );
		}
		this.publish();
	}

	clip( byHand = false ) {
		const axis = $( 'clip-axis' ).value;
		$( 'clip-position' ).disabled = ! axis;
		const fraction = Number( $( 'clip-position' ).value );
		this.viewer.setClipping( axis || null, fraction );
		status.structures.clip = axis ? { axis, fraction } : null;
		if ( byHand ) this.onChange();
	}

	async download( format ) {
		const index = this.viewer.selected;
		if ( index == null || ! this.canDownload ) return;
		const part = this.viewer.parts[ index ];
		if ( format === 'stl' ) {
			const { STLExporter } = await import( 'three/addons/exporters/STLExporter.js' );
			const data = new STLExporter().parse( this.viewer.partMesh( index, 'lps' ), { binary: true } );
			save( data, fileName( part.name, 'stl' ), 'model/stl' );
		} else {
			const { GLTFExporter } = await import( 'three/addons/exporters/GLTFExporter.js' );
			const data = await new GLTFExporter().parseAsync( this.viewer.partMesh( index, 'world' ), { binary: true } );
			save( data, fileName( part.name, 'glb' ), 'model/gltf-binary' );
		}
	}

	// window.__miss.structures: what the browser tests read.
	publish() {
		status.structures.parts = this.viewer.parts.map( ( p ) => ( {
			name: p.name, visible: p.mesh.visible, opacity: p.material.opacity,
			color: hex( p.material.color ), volume_ml: p.volume_ml ?? null, area_cm2: p.area_cm2 ?? null,
		} ) );
		status.structures.selected = this.viewer.selected;
	}
}
