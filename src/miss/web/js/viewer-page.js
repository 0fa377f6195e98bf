// Viewer page: waits for the model if it is still being built, draws it in
// GLB or VRML mode, and lists its statistics and downloads.

import { FORMATS, api, urls, watchModel } from './api.js';
import { el, formatBytes, formatCount, formatMm, formatSeconds } from './format.js';
import { percent, renderStages, stageLabel } from './job.js';
import { BACKGROUNDS, ModelViewer } from './viewer.js';

const $ = ( id ) => document.getElementById( id );
const modelId = decodeURIComponent( location.pathname.split( '/' ).filter( Boolean ).pop() );

const FORMAT_NAMES = {
	glb: 'glTF binary', wrl: 'VRML 97', wrz: 'VRML gzip', x3d: 'X3D', stl: 'STL', ply: 'PLY', obj: 'OBJ',
};
const MODE_NOTES = {
	glb: 'glTF binary, as browsers load 3-D today.',
	vrml: 'The 1998 deliverable: the VRML 97 file, drawn by three.js’s VRMLLoader with no plug-in.',
};

// What browser tests (and curious developers) read: set once a model is drawn.
const status = { ready: false, mode: null, triangles: 0, background: 'dark', backgroundColor: BACKGROUNDS.dark };
window.__miss = status;

let viewer = null;

function overlay( title, text = '', { progress = null, model = null } = {} ) {
	$( 'overlay' ).hidden = false;
	$( 'overlay-title' ).textContent = title;
	$( 'overlay-text' ).textContent = text;
	$( 'overlay-progress' ).hidden = progress == null;
	if ( progress != null ) $( 'overlay-progress' ).value = progress;
	$( 'overlay-stages' ).hidden = ! model;
	if ( model ) renderStages( $( 'overlay-stages' ), model );
}

function row( label, value ) {
	return el( 'tr', {}, el( 'th', {}, label ), el( 'td', {}, value ) );
}

function fillStats( model ) {
	const s = model.stats || {};
	const d = s.decimation || {};
	const seconds = s.seconds || {};
	const total = seconds.total ?? Object.values( seconds ).reduce( ( a, b ) => a + b, 0 );
	$( 'stats' ).replaceChildren(
		row( 'Triangles', formatCount( s.triangles ) ),
		row( 'Vertices', formatCount( s.vertices ) ),
		d.triangles_before != null ? row( 'Before decimation', formatCount( d.triangles_before ) ) : null,
		row( 'Max error', formatMm( d.max_error_mm ) ),
		row( 'Mean error', formatMm( d.mean_error_mm, 4 ) ),
		...Object.entries( seconds ).filter( ( [ k ] ) => k !== 'total' ).map( ( [ k, v ] ) => row( `Time: ${k}`, formatSeconds( v ) ) ),
		row( 'Time: total', formatSeconds( total ) ),
		row( 'Drawn now', el( 'span', { id: 'drawn' }, '–' ) ),
	);
	const p = model.params || {};
	const slices = p.start_slice || p.end_slice ? `${p.start_slice ?? 1} – ${p.end_slice ?? 'last'}` : 'all';
	$( 'params' ).replaceChildren(
		row( 'Threshold', p.level ),
		row( 'Sample rate', Array.isArray( p.sample_rate ) ? p.sample_rate.join( ', ' ) : p.sample_rate ),
		row( 'Slices', slices ),
		row( 'Decimation', p.decimate ),
		row( 'Error bound', p.error_bound ),
		row( 'Reduce', p.reduce ),
	);
	$( 'model-meta' ).textContent = `${formatCount( s.triangles )} triangles`;
}

function fillDownloads( model ) {
	const bytes = model.stats?.bytes || {};
	$( 'downloads' ).replaceChildren( ...FORMATS.map( ( fmt ) => el( 'a.button.small', {
		href: urls.download( modelId, fmt ), download: '', dataset: { format: fmt }, title: FORMAT_NAMES[ fmt ],
	}, el( 'span', {}, `.${fmt}` ), el( 'span.size', {}, bytes[ fmt ] != null ? formatBytes( bytes[ fmt ] ) : FORMAT_NAMES[ fmt ] ) ) ) );
}

async function show( mode ) {
	status.ready = false;
	status.mode = mode;
	for ( const b of document.querySelectorAll( '[data-mode]' ) ) b.setAttribute( 'aria-pressed', String( b.dataset.mode === mode ) );
	$( 'mode-note' ).textContent = MODE_NOTES[ mode ];
	const url = new URL( location.href );
	url.searchParams.set( 'mode', mode );
	history.replaceState( null, '', url );
	const file = mode === 'vrml' ? 'wrl' : 'glb';
	overlay( `Loading ${file.toUpperCase()}…`, '', { progress: 0 } );
	try {
		const triangles = await viewer.load( urls.download( modelId, file ), mode, ( e ) => {
			if ( e.lengthComputable ) $( 'overlay-progress' ).value = e.loaded / e.total;
			$( 'overlay-text' ).textContent = formatBytes( e.loaded );
		} );
		if ( status.mode !== mode ) return; // the user switched again meanwhile
		$( 'overlay' ).hidden = true;
		$( 'drawn' ).textContent = `${formatCount( triangles )} △ (${mode.toUpperCase()})`;
		Object.assign( status, { ready: true, triangles } );
	} catch ( err ) {
		overlay( `Could not show the ${file.toUpperCase()} file`, err.message || String( err ) );
		status.error = err.message || String( err );
	}
}

function setBackground( name ) {
	viewer.setBackground( name );
	status.background = name;
	status.backgroundColor = BACKGROUNDS[ name ];
	$( 'background' ).textContent = name === 'dark' ? 'Light background' : 'Dark background';
	localStorage.setItem( 'miss.background', name );
}

async function waitUntilBuilt( model ) {
	if ( model.status === 'done' ) return model;
	const update = ( m ) => overlay( `Building the model: ${stageLabel( m.status === 'queued' ? 'queued' : m.stage )}`, percent( m ), { progress: m.progress || 0, model: m } );
	update( model );
	return watchModel( modelId, update );
}

async function main() {
	viewer = new ModelViewer( $( 'stage' ) );
	setBackground( localStorage.getItem( 'miss.background' ) === 'light' ? 'light' : 'dark' );
	$( 'fit' ).addEventListener( 'click', () => viewer.fit() );
	$( 'background' ).addEventListener( 'click', () => setBackground( status.background === 'dark' ? 'light' : 'dark' ) );
	for ( const b of document.querySelectorAll( '[data-mode]' ) ) b.addEventListener( 'click', () => status.mode !== b.dataset.mode && show( b.dataset.mode ) );
	try {
		let model = await api.model( modelId );
		api.volume( model.volume ).then( ( v ) => {
			$( 'volume-link' ).textContent = v.name;
			$( 'volume-link' ).href = urls.volumePage( v.id );
			document.title = `MISS · ${v.name}`;
		} ).catch( () => {} );
		model = await waitUntilBuilt( model );
		fillStats( model );
		fillDownloads( model );
		await show( new URLSearchParams( location.search ).get( 'mode' ) === 'vrml' ? 'vrml' : 'glb' );
	} catch ( err ) {
		overlay( 'This model cannot be shown', err.message || String( err ) );
		status.error = err.message || String( err );
	}
}

main();
