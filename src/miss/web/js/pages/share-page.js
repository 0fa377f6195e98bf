// A share link's page (/s/{token}, model.html as a guest): the viewer without an
// account. Everything comes from /s/{token}/...: who shared what until when, the
// model's provenance, its structures and the files the link allows; a link that
// allows annotating joins the room.

import { request } from '../api.js';
import { Consultation } from '../room/consult.js';
import { el, fill, showNotes } from '../format.js';
import { fillDownloads, fillStats, overlay, setupDisplay, surfacesOf } from '../viewer/viewer-ui.js';
import { status } from '../test-hooks.js';
import { StructuresPanel } from '../viewer/structures-panel.js';
import { ModelViewer } from '../viewer/viewer.js';
import { VolumePanel } from '../viewer/volume-panel.js';
import { addressViews, linkCamera } from '../viewer/deep-link.js';
import { LinkedSlices } from '../viewer/linked-slices.js';
import { rememberLink } from '../shared-links.js';

const $ = ( id ) => document.getElementById( id );
const token = decodeURIComponent( location.pathname.split( '/' )[ 2 ] || '' );
const base = `/s/${encodeURIComponent( token )}`;

function row( label, value, title ) {
	return el( 'tr', {}, el( 'th', {}, label ), el( 'td', title ? { title } : {}, value ) );
}

function when( iso ) {
	return new Date( iso ).toLocaleString( [], { dateStyle: 'medium', timeStyle: 'short' } );
}

function info() {
	return request( 'GET', `${base}/info`, undefined, { login: false } );
}

function showShare( data ) {
	const s = data.share;
	const rights = [ 'view', s.can_view_volume ? 'the scan in 3-D' : null, s.can_annotate ? 'consult' : null, s.can_download ? 'download' : null ].filter( Boolean ).join( ', ' );
	fill( $( 'share-facts' ),
		row( 'Shared by', s.shared_by ),
		s.message ? row( 'Message', s.message ) : null,
		row( 'Expires', when( s.expires ) ),
		row( 'You may', rights ),
		row( 'Scan', `${data.volume.modality || 'volume'} · ${( data.volume.dims || [] ).join( '×' )}` ) );
	$( 'share-title' ).textContent = `Shared by ${s.shared_by} · until ${when( s.expires )}`;
	$( 'burned-in' ).hidden = ! data.volume.burned_in_annotation;
	showNotes( $( 'volume-notes' ), data.volume );
	$( 'download-section' ).hidden = ! s.can_download;
}

// The job's parameters in words, as the owner's Parameters table says them.
function described( params ) {
	if ( ! params || typeof params !== 'object' ) return String( params ?? '' );
	const words = [ `surfaces: ${surfacesOf( params )}` ];
	if ( params.sample_rate != null ) words.push( `sample rate ${[].concat( params.sample_rate ).join( ', ' )}` );
	if ( params.decimate ) words.push( `decimation ${params.decimate}${params.error_bound != null ? `, error bound ${params.error_bound} of the diagonal` : ''}` );
	return words.join( ' · ' );
}

function showProvenance( p ) {
	let params = p.parameters;
	try {
		params = typeof params === 'string' ? JSON.parse( params ) : params;
	} catch ( err ) { /* shown as it came */ }
	const brief = described( params );
	const hash = p.source_sha256 || '';
	fill( $( 'provenance' ),
		row( 'Software', p.software || '–' ),
		row( 'Made', p.created ? when( p.created ) : '–' ),
		row( 'Source hash', hash ? `sha256:${hash.slice( 0, 16 )}…` : '–', hash ),
		row( 'Parameters', el( 'span.wrap', {}, brief ) ) );
}

// A volume link covers several models: ?model=ID picks one, the newest by default.
function pickModel( models ) {
	const done = models.filter( ( m ) => m.status === 'done' );
	const wanted = new URLSearchParams( location.search ).get( 'model' );
	const chosen = done.find( ( m ) => m.id === wanted ) || done[ done.length - 1 ] || models[ 0 ];
	if ( done.length > 1 ) {
		$( 'model-choice' ).hidden = false;
		$( 'model-select' ).replaceChildren( ...done.map( ( m ) => el( 'option', { value: m.id, selected: m === chosen },
			`level ${m.params.level}, sample rate ${m.params.sample_rate}, ${m.params.decimate}` ) ) );
		$( 'model-select' ).addEventListener( 'change', ( e ) => {
			const url = new URL( location.href );
			url.searchParams.set( 'model', e.target.value );
			location.assign( url );
		} );
	}
	return chosen;
}

export async function start() {
	const viewer = new ModelViewer( $( 'stage' ) );
	let model = null;
	let consult = null;
	const structures = new StructuresPanel( viewer );
	const onLoaded = () => {
		structures.refresh();
		consult?.modelLoaded();
	};
	const urlOf = ( fmt ) => ( fmt === 'lod' ? model.lod : model.files[ fmt ]?.url || `${base}/models/${model.id}/model.${fmt}` );
	const display = setupDisplay( viewer, urlOf, { canVrml: () => Boolean( model?.files.wrl ), onLoaded } );
	try {
		const data = await info();
		showShare( data );
		// a signed-in colleague finds this link again under Shared with me in the library
		const signedIn = document.cookie.split( '; ' ).some( ( c ) => c.startsWith( 'miss_csrf=' ) );
		if ( signedIn ) rememberLink( data.share.id, location.pathname );
		model = pickModel( data.models );
		if ( ! model || model.status !== 'done' ) throw new Error( 'the shared model is not finished yet; reload this page in a minute.' );
		document.title = `MISS · Shared model · ${data.share.shared_by}`;
		fillStats( model, { timings: false } );
		structures.setStats( model.stats );
		structures.canDownload = data.share.can_download; // a part on its own is a download too
		fillDownloads( model.files );
		const vrml = document.querySelector( '[data-mode=vrml]' );
		vrml.disabled = ! model.files.wrl;
		if ( vrml.disabled ) vrml.title = 'This link includes the GLB only (no downloads).';
		showProvenance( model.provenance );
		const volumePanel = data.share.can_view_volume ? new VolumePanel( viewer, `${base}/voxels` ) : null;
		const volumeView = volumePanel && addressViews().has( 'volume' );
		const slices = volumePanel ? new LinkedSlices( viewer, volumePanel ) : null;
		const slicesShown = slices && addressViews().has( 'slices' ) ? slices.show( true ) : null;
		if ( volumeView ) volumePanel.prefetch(); // arrives while the model loads
		if ( data.share.can_annotate ) {
			// a colleague signed in here joins under their own name, not "Guest" (asked only
			// with a session's cookie: a guest's browser would log a 401)
			const me = signedIn ? await request( 'GET', '/api/auth/me', undefined, { login: false } ).catch( () => null ) : null;
			consult = new Consultation( { viewer, modelId: model.id, container: $( 'room' ), share: token, guest: true, structures, volume: volumePanel, slices, signedIn: me?.name } );
		}
		$( 'room' ).hidden = ! data.share.can_annotate;
		$( 'view-only' ).hidden = data.share.can_annotate;
		await display( new URLSearchParams( location.search ).get( 'mode' ) );
		linkCamera( viewer ); // a link with ?cam= opens on the view it was sent with
		if ( volumeView ) await volumePanel.show( true );
		await slicesShown;
	} catch ( err ) {
		overlay( 'This shared model cannot be shown', err.message || String( err ) );
		status.error = err.message || String( err );
	}
}
