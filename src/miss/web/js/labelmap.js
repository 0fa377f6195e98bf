// Volume page: a label map laid over the volume (e.g. TotalSegmentator output).
// Upload it, tick labels (name and voxel count), and Generate sends `labels`.

import { request } from './api.js';
import { el, formatCount } from './format.js';

const path = ( id ) => `/api/volumes/${encodeURIComponent( id )}/labelmap`;

export class LabelMapPanel {
	// root: the section element; volume: GET /api/volumes/{id}; onError(err or null);
	// onOverlay(map): the map's hash when the slices should lay its colours over (a map
	// is there and "show on the slices" is ticked), else null.
	constructor( root, volume, onError, onOverlay = () => {} ) {
		this.root = root;
		this.volumeId = volume.id;
		this.onError = onError;
		this.onOverlay = onOverlay;
		this.overlay = root.querySelector( '.label-overlay input' );
		this.overlay.addEventListener( 'change', () => this.onOverlay( this.overlay.checked ? this.sha : null ) );
		this.list = root.querySelector( '.label-list' );
		this.all = root.querySelector( '.label-all' );
		this.file = root.querySelector( 'input[type=file]' );
		this.remove = root.querySelector( '.label-remove' );
		this.status = root.querySelector( '.label-status' );
		this.file.addEventListener( 'change', () => this.upload() );
		this.remove.addEventListener( 'click', () => this.clear() );
		this.all.addEventListener( 'change', () => {
			for ( const box of this.boxes() ) box.checked = this.all.checked;
		} );
		this.show( volume.labelmap );
	}

	boxes() {
		return [ ...this.list.querySelectorAll( 'input[type=checkbox]' ) ];
	}

	show( labelmap ) {
		const labels = labelmap?.labels || [];
		this.status.textContent = labelmap ? `${labels.length} labels${labelmap.table ? ` · names from ${labelmap.table}` : ''}` : 'none';
		this.all.checked = false;
		this.all.closest( 'label' ).hidden = ! labelmap;
		this.remove.hidden = ! labelmap;
		this.overlay.closest( 'label' ).hidden = ! labelmap;
		this.sha = labelmap ? labelmap.sha256 || '1' : null;
		this.onOverlay( this.overlay.checked ? this.sha : null );
		this.list.replaceChildren( ...labels.map( ( e ) => {
			const box = el( 'input', { type: 'checkbox', value: String( e.label ) } );
			box.addEventListener( 'change', () => {
				this.all.checked = this.boxes().every( ( b ) => b.checked );
			} );
			const swatch = el( 'span.swatch', {} );
			if ( e.color?.length === 3 ) swatch.style.background = `rgb(${e.color.map( ( c ) => Math.round( c * 255 ) ).join( ',' )})`;
			return el( 'li', {}, el( 'label', {}, box, swatch, ` ${e.label} ${e.name} `, el( 'span.muted', {}, `${formatCount( e.voxels )} voxels` ) ) );
		} ) );
	}

	// What Generate sends: "all", a list of ids, or null when nothing is ticked.
	labels() {
		const ticked = this.boxes().filter( ( b ) => b.checked ).map( ( b ) => Number( b.value ) );
		if ( ! ticked.length ) return null;
		return this.all.checked ? 'all' : ticked;
	}

	async upload() {
		const file = this.file.files[ 0 ];
		if ( ! file ) return;
		this.onError( null );
		this.status.textContent = 'reading…';
		const form = new FormData();
		form.append( 'file', file );
		try {
			const volume = await request( 'POST', path( this.volumeId ), form );
			this.show( volume.labelmap );
		} catch ( err ) {
			this.onError( err );
			this.status.textContent = 'upload failed';
		} finally {
			this.file.value = '';
		}
	}

	async clear() {
		this.onError( null );
		try {
			await request( 'DELETE', path( this.volumeId ) );
			this.show( null );
		} catch ( err ) {
			this.onError( err );
		}
	}
}
