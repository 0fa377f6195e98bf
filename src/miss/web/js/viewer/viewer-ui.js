// What the owner's viewer and a share link's viewer have in common: the loading
// overlay, the statistics and parameters, the download buttons, GLB/VRML mode
// and the background.

import { el, fill, formatBytes, formatCount, formatMm, formatSeconds } from '../format.js';
import { renderStages } from '../job.js';
import { BACKGROUNDS } from './viewer.js';
import { status } from '../test-hooks.js';

const $ = ( id ) => document.getElementById( id );

const MODE_NOTES = {
	glb: 'glTF binary, as browsers load 3-D today.',
	vrml: 'The 1998 deliverable: the VRML 97 file, drawn by three.js’s VRMLLoader with no plug-in.',
};

Object.assign( status, { background: 'dark', backgroundColor: BACKGROUNDS.dark } );

export function overlay( title, text = '', { progress = null, model = null } = {} ) {
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

// The stages' seconds under their own names, but those a physician would not guess.
const TIME_LABELS = { viewer: 'waiting for the viewer to draw' };

// What a job made its surfaces of, in words: its thresholds (each part's name and level),
// or the labels of a label map.
export function surfacesOf( p ) {
	const labels = ( l ) => ( l === 'all' || l == null ? 'all labels' : `labels ${[].concat( l ).join( ', ' )}` );
	if ( p.parts?.length ) {
		return p.parts.map( ( x ) => ( x.level != null ? `${x.name || 'part'} at ${x.level}` : `${x.name ? `${x.name}: ` : ''}${labels( x.labels )}` ) ).join( '; ' );
	}
	if ( p.labels != null ) return labels( p.labels );
	return p.levels?.length ? p.levels.join( ', ' ) : String( p.level ?? '–' );
}

// The model's figures and parameters; `timings`: the job's own times (the owner's
// business; a guest reads the model, not how long the server took).
export function fillStats( model, { timings = true } = {} ) {
	const s = model.stats || {};
	const d = s.decimation || {};
	const seconds = s.seconds || {};
	const total = seconds.total ?? Object.values( seconds ).reduce( ( a, b ) => a + b, 0 );
	fill( $( 'stats' ),
		row( 'Triangles', formatCount( s.triangles ) ),
		row( 'Vertices', formatCount( s.vertices ) ),
		d.triangles_before != null ? row( 'Before decimation', formatCount( d.triangles_before ) ) : null,
		row( 'Max error', formatMm( d.max_error_mm ) ),
		row( 'Mean error', formatMm( d.mean_error_mm, 4 ) ),
		d.bound_mm ? row( 'Error bound held', boundHeld( d ) ) : null,
		smoothingRow( s.parts || [] ),
		...( timings ? Object.entries( seconds ).filter( ( [ k ] ) => k !== 'total' ).map( ( [ k, v ] ) => row( `Time: ${TIME_LABELS[ k ] || k}`, formatSeconds( v ) ) ) : [] ),
		timings ? row( 'Time: total', formatSeconds( total ) ) : null,
		row( 'Drawn now', el( 'span', { id: 'drawn' }, '–' ) ),
	);
	const p = model.params || {};
	const slices = p.start_slice || p.end_slice ? `${p.start_slice ?? 1} – ${p.end_slice ?? 'last'}` : 'all';
	fill( $( 'params' ),
		row( p.parts?.length || p.levels?.length > 1 || p.labels != null ? 'Surfaces' : 'Threshold', surfacesOf( p ) ),
		p.components && p.components !== 'all' ? row( 'Components', `${p.components}${p.min_size_mm3 ? ` ≥ ${p.min_size_mm3} mm³` : ''}` ) : null,
		s.parts ? row( 'Parts', s.parts.length ) : null,
		row( 'Sample rate', Array.isArray( p.sample_rate ) ? p.sample_rate.join( ', ' ) : p.sample_rate ),
		row( 'Slices', slices ),
		row( 'Decimation', madeBy( p.decimate, d.finished_with ) ),
		row( 'Error bound', p.error_bound ),
		row( 'Reduce', p.reduce ),
	);
	$( 'model-meta' ).textContent = `${formatCount( s.triangles )} triangles`;
}

// How far smoothing moved the surface before decimation (the parts' largest and mean
// vertex displacement): its effect, beside the bound the decimation held.
function smoothingRow( parts ) {
	const smoothed = parts.filter( ( p ) => p.smoothing_max_mm != null );
	if ( ! smoothed.length ) return null;
	const most = Math.max( ...smoothed.map( ( p ) => p.smoothing_max_mm ) );
	const mean = smoothed.reduce( ( a, p ) => a + p.smoothing_mean_mm * p.vertices, 0 ) / smoothed.reduce( ( a, p ) => a + p.vertices, 0 );
	return row( 'Smoothing moved the surface', `≤ ${formatMm( most )} (mean ${formatMm( mean, 3 )})` );
}

// Whether the model is within the bound it was given, and what stopped the decimation.
function boundHeld( d ) {
	if ( d.bound_held == null ) return `not checked (bound ${formatMm( d.bound_mm )})`;
	if ( ! d.bound_held ) return `no: over ${formatMm( d.bound_mm )}`;
	// quadric's own runs (the paper's schedule) are held where they are measured only
	const where = d.finished_with === 'quadric' ? ' at the measured points' : '';
	const stop = d.stopped_by === 'bound' ? 'the bound' : 'the reduce target';
	return `yes: within ${formatMm( d.bound_mm )}${where}; stopped by ${stop}`;
}

// The method asked for, and the one that made the model when they differ (a held bound
// is schroeder's model whatever was asked for; a model kept whole was not decimated).
function madeBy( asked, made ) {
	if ( ! made || made === asked ) return asked;
	return made === 'none' ? `${asked} (kept whole)` : `${asked} asked; made by ${made}`;
}

// files: {fmt: {url, bytes}} -- every format for the owner, what a link allows for a guest.
// files: the model's files as the server lists them (its formats, in its order, each
// with url, bytes, a one-line description and its button's label: ".stl", or words
// where the extension alone would not tell, as for the plain GLB).
export function fillDownloads( files ) {
	shownFiles = files || {};
	const phone = onPhone();
	const link = ( [ fmt, file ] ) => {
		const label = file.label || `.${fmt}`;
		const big = phone && file.bytes > BIG_ON_PHONE;
		// words take the whole row, so that they read on one line beside the size
		return el( label === `.${fmt}` && ! big ? 'a.button.small' : 'a.button.small.wide', {
			href: file.url, download: '', dataset: { format: fmt }, title: file.description,
		}, el( 'span', {}, label ), el( 'span.size', {}, formatBytes( file.bytes ) ),
		big ? el( 'span.warning', {}, 'large for a phone' ) : null );
	};
	const entries = Object.entries( files || {} );
	if ( ! phone ) return $( 'downloads' ).replaceChildren( ...entries.map( link ) );
	// A phone: the compact GLB (what the viewer draws, and phones open) first; the formats
	// for desktop tools (VRML, STL, OBJ, often tens of megabytes) folded behind it.
	const first = entries.filter( ( [ fmt ] ) => fmt === 'glb' );
	const rest = entries.filter( ( [ fmt ] ) => fmt !== 'glb' );
	$( 'downloads' ).replaceChildren( ...first.map( link ), rest.length ? el( 'details.more-formats', {},
		el( 'summary', {}, `More formats (${rest.length}), for desktop tools` ), ...rest.map( link ) ) : '' );
}

// The model's files as last listed (their sizes: a big VRML file is asked about first).
let shownFiles = {};
// A VRML file larger than this (bytes) is loaded only once the person agrees.
const VRML_ASK_BYTES = 30 * 2 ** 20;

// Whether to go on to a VRML file of this size: it is the 1998 deliverable, text a dozen
// times the GLB's size, which the browser must read whole before it draws.
function vrmlWanted() {
	// Not made yet (formats are made on their first download): about 48 bytes a triangle,
	// as MISS writes them (a 2.04 M-triangle model's was 98 MB).
	const known = shownFiles.wrl?.bytes;
	const bytes = known || 48 * ( status.triangles || 0 );
	if ( bytes <= ( status.vrmlAskBytes ?? VRML_ASK_BYTES ) ) return true; // the tests lower it
	const glb = shownFiles.glb?.bytes ? ` (the GLB, which shows the same model, is ${formatBytes( shownFiles.glb.bytes )})` : '';
	status.vrmlAsked = bytes;
	return confirm( `The VRML file is ${known ? '' : 'about '}${formatBytes( bytes )}${glb}: your browser must fetch and read all of it, which takes time and memory. Load it anyway?` );
}

// A phone (a narrow screen, or a touch screen held sideways; not a tablet): what it is
// offered is what it can use.
export const onPhone = () => matchMedia( '(max-width: 600px), (pointer: coarse) and (hover: none) and (max-height: 500px)' ).matches;
// A file this large (bytes) is marked as such on a phone: mobile data, and a phone's memory.
const BIG_ON_PHONE = 50 * 2 ** 20;

// Loads the GLB or the VRML file (urlOf(fmt)) into the viewer; resolves once
// drawn, after calling onLoaded(). drawn: the GLB is on the stage already (drawn
// while the job was finishing), so GLB mode only says so. A large model's levels of
// detail (urlOf('lod'), its tileset) stand in for its GLB: coarse first, refined in view.
export async function show( viewer, mode, urlOf, onLoaded = () => {}, { drawn = false } = {} ) {
	status.ready = false;
	status.mode = mode;
	for ( const b of document.querySelectorAll( '[data-mode]' ) ) b.setAttribute( 'aria-pressed', String( b.dataset.mode === mode ) );
	$( 'mode-note' ).textContent = MODE_NOTES[ mode ];
	const url = new URL( location.href );
	url.searchParams.set( 'mode', mode );
	history.replaceState( null, '', url );
	const file = mode === 'vrml' ? 'wrl' : 'glb';
	const lod = mode === 'glb' ? urlOf( 'lod' ) : null;
	const onStage = drawn && mode === 'glb'; // the levels of detail, for a large model
	if ( ! onStage ) overlay( `Loading ${file.toUpperCase()}…`, '', { progress: 0 } );
	try {
		const triangles = onStage ? status.triangles : await viewer.load( lod || urlOf( file ), lod ? 'lod' : mode, ( e ) => {
			if ( e.lengthComputable ) $( 'overlay-progress' ).value = e.loaded / e.total;
			$( 'overlay-text' ).textContent = formatBytes( e.loaded );
		}, { keepView: drawn } );
		if ( status.mode !== mode ) return; // the user switched again meanwhile
		$( 'overlay' ).hidden = true;
		$( 'drawn' ).textContent = `${formatCount( triangles )} △ (${lod ? 'levels of detail' : mode.toUpperCase()})`;
		// Levels of detail: what each frame draws, as the view refines and coarsens.
		viewer.onDrawn = lod ? ( n ) => ( $( 'drawn' ).textContent = `${formatCount( n )} △ (levels of detail)` ) : null;
		onLoaded();
		Object.assign( status, { ready: true, triangles } );
	} catch ( err ) {
		overlay( `Could not show the ${file.toUpperCase()} file`, err.message || String( err ) );
		status.error = err.message || String( err );
	}
}

function setBackground( viewer, name ) {
	viewer.setBackground( name );
	status.background = name;
	status.backgroundColor = BACKGROUNDS[ name ];
	$( 'background' ).textContent = name === 'dark' ? 'Light background' : 'Dark background';
	localStorage.setItem( 'miss.background', name );
}

// Wires Fit, the background toggle and the GLB/VRML buttons; returns
// show(mode). canVrml(): is the .wrl there (a view-only link has the GLB alone)?
export function setupDisplay( viewer, urlOf, { canVrml = () => true, onLoaded = () => {} } = {} ) {
	setBackground( viewer, localStorage.getItem( 'miss.background' ) === 'light' ? 'light' : 'dark' );
	$( 'fit' ).addEventListener( 'click', () => viewer.fit() );
	$( 'background' ).addEventListener( 'click', () => setBackground( viewer, status.background === 'dark' ? 'light' : 'dark' ) );
	for ( const b of document.querySelectorAll( '[data-mode]' ) ) {
		b.addEventListener( 'click', () => status.mode !== b.dataset.mode && canVrml()
			&& ( b.dataset.mode !== 'vrml' || vrmlWanted() ) && show( viewer, b.dataset.mode, urlOf, onLoaded ) );
		// VRML is the 1998 deliverable for desktop tools: a phone draws the GLB, a tenth the size.
		if ( b.dataset.mode === 'vrml' && onPhone() ) b.hidden = true;
	}
	status.cameraLps = () => viewer.pose();
	return ( mode, options ) => show( viewer, mode === 'vrml' && canVrml() && vrmlWanted() ? 'vrml' : 'glb', urlOf, onLoaded, options );
}
