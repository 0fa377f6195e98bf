// Volume page: three orthogonal slices, window/level, the histogram with a
// threshold, the 1998 form's choices (start/end slice, sample rate,
// decimation, error bound, reduce rate) and Generate, which opens the model's page.

import { showSession } from '../session.js';
import { api, urls, watchModel } from '../api.js';
import { describeModel, modelTitle } from '../job.js';
import { describeVolume, el, formatCount, showNotes } from '../format.js';
import { Histogram, binEdges } from '../histogram.js';
import { LabelMapPanel } from '../labelmap.js';
import { SliceRange } from '../range.js';
import { checkLevel, checkSampleRate, checkSlices, parseSampleRate, showCheck } from '../form-checks.js';
import { showPrivacy } from '../privacy.js';
import { SliceView } from '../slices.js';

const $ = ( id ) => document.getElementById( id );
const volumeId = decodeURIComponent( location.pathname.split( '/' ).filter( Boolean ).pop() );

// labels: the label map's hash while its colours are laid over the slices, else null.
const state = { window: 400, level: 40, threshold: 0, labels: null };
let views = [];
let histogram = null;
let range = null;
let labelMap = null;
// The volume's values (lo, hi) and their units: a level must lie between lo and hi.
const limits = { range: null, units: '' };

function showError( err ) {
	$( 'form-error' ).textContent = err ? err.message || String( err ) : '';
	$( 'form-error' ).hidden = ! err;
}

// Value at a cumulative fraction of the voxels; gives a contrast window for
// MR and other scans with no standard one.
// The server may send presets as {name: level} or as [{name, level, basis}].
function presetLevels( hist, volume ) {
	const raw = hist.presets ?? volume.presets ?? {};
	if ( ! Array.isArray( raw ) ) return raw;
	return Object.fromEntries( raw.map( ( p ) => [ p.name, p.level ] ) );
}

function quantile( hist, q ) {
	const total = hist.counts.reduce( ( a, b ) => a + b, 0 );
	let acc = 0;
	for ( let i = 0; i < hist.counts.length; i ++ ) {
		acc += hist.counts[ i ];
		if ( acc >= q * total ) return hist.bins[ i + 1 ];
	}
	return hist.bins[ hist.bins.length - 1 ];
}

function windowPresets( volume, hist ) {
	const [ lo, hi ] = volume.range || [ hist.bins[ 0 ], hist.bins[ hist.bins.length - 1 ] ];
	const p1 = quantile( hist, 0.01 );
	const p99 = quantile( hist, 0.99 );
	const server = volume.window || hist.window;
	const presets = [ [ 'contrast (1–99 %)', Math.max( 1, p99 - p1 ), ( p1 + p99 ) / 2 ], [ 'full range', Math.max( 1, hi - lo ), ( lo + hi ) / 2 ] ];
	if ( server ) presets.unshift( [ 'default', server.window, server.level ] );
	if ( isCT( volume, hist ) ) {
		presets.unshift( [ 'soft tissue', 400, 40 ], [ 'bone', 2000, 500 ], [ 'brain', 80, 40 ], [ 'lung', 1500, - 600 ] );
	}
	return presets.map( ( [ name, w, l ] ) => ( { name, window: Math.round( w * 100 ) / 100, level: Math.round( l * 100 ) / 100 } ) );
}

function isCT( volume, hist ) {
	return ( volume.modality || '' ).toUpperCase() === 'CT' || hist.units === 'HU';
}

function refreshSlices( delay ) {
	for ( const view of views ) view.setDisplay( { ...state }, delay );
}

function setupWindowLevel( volume, hist ) {
	const presets = windowPresets( volume, hist );
	const select = $( 'wl-preset' );
	select.append( ...presets.map( ( p, i ) => el( 'option', { value: i }, `${p.name} (W ${p.window}, L ${p.level})` ) ) );
	const apply = ( p ) => {
		state.window = p.window;
		state.level = p.level;
		$( 'window' ).value = p.window;
		$( 'level' ).value = p.level;
	};
	apply( presets[ 0 ] );
	select.value = '0';
	select.addEventListener( 'change', () => {
		if ( select.value === '' ) return;
		apply( presets[ Number( select.value ) ] );
		refreshSlices( 0 );
	} );
	for ( const id of [ 'window', 'level' ] ) {
		$( id ).addEventListener( 'input', () => {
			const v = Number( $( id ).value );
			if ( $( id ).value === '' || ! Number.isFinite( v ) || ( id === 'window' && v <= 0 ) ) return;
			state[ id ] = v;
			select.value = '';
			refreshSlices( 250 );
		} );
	}
}

// What a level measures, in the form's words: "Density (HU)" on CT, "Intensity" on MR, as
// the server decided from the header or, without a modality, from the histogram.
function showScale( volume, presets ) {
	const scale = volume.scale || {};
	$( 'level-label' ).textContent = scale.label || 'Level';
	if ( scale.reason ) $( 'level-label' ).title = `${scale.kind || ''}: ${scale.reason}`;
	const [ low, high ] = Object.entries( presets ).sort( ( a, b ) => a[ 1 ] - b[ 1 ] );
	if ( low && high ) {
		$( 'structures-hint' ).textContent = `The level above is the first; add levels (e.g. ${low[ 0 ]} ${low[ 1 ]}, translucent, and ${high[ 0 ]} ${high[ 1 ]}) for one scene of named parts.`;
	}
}

function setupThreshold( hist, volume ) {
	const presets = presetLevels( hist, volume );
	const names = Object.keys( presets );
	const units = hist.units ?? volume.units ?? '';
	showScale( volume, presets );
	$( 'units' ).textContent = units;
	Object.assign( limits, { range: volume.range || [ hist.bins[ 0 ], hist.bins[ hist.bins.length - 1 ] ], units } );
	const buttons = [ ...names, 'custom' ].map( ( name ) => el( 'button.small', {
		type: 'button', dataset: { preset: name }, 'aria-pressed': 'false',
		onclick: () => ( name === 'custom' ? $( 'threshold' ).focus() : setThreshold( presets[ name ], 0 ) ),
	}, name === 'custom' ? 'custom' : `${name} ${presets[ name ]}` ) );
	$( 'presets' ).replaceChildren( ...buttons );

	const setThreshold = ( value, delay ) => {
		state.threshold = value;
		$( 'threshold' ).value = value;
		$( 'threshold-readout' ).textContent = `${value} ${units}`;
		const active = names.find( ( n ) => presets[ n ] === value ) || 'custom';
		for ( const b of buttons ) b.setAttribute( 'aria-pressed', String( b.dataset.preset === active ) );
		if ( histogram && histogram.value !== value ) histogram.setValue( value );
		const first = document.querySelector( '#structure-list [data-first] .structure-level' );
		if ( first ) first.value = value;
		refreshSlices( delay );
	};

	// The server lists the default first: bone on CT, the outer surface (skin) on MR.
	const start = presets[ names[ 0 ] ] ?? quantile( hist, 0.9 );
	histogram = new Histogram( $( 'histogram' ), hist, {
		value: start,
		onInput: ( v ) => setThreshold( v, 150 ), // live tint while dragging, debounced reloads
		onChange: ( v ) => setThreshold( v, 0 ),
	} );
	// Checked as typed against the volume's values: a level outside them has no surface.
	$( 'threshold' ).addEventListener( 'input', () => {
		const problem = checkLevel( $( 'threshold' ).value, limits.range, units );
		showCheck( $( 'threshold' ), problem );
		if ( ! problem ) setThreshold( Number( $( 'threshold' ).value ), 250 );
	} );
	setThreshold( start, 0 );
}

function setupViews( volume ) {
	const [ nx, ny, nz ] = volume.dims;
	const counts = { sagittal: nx, coronal: ny, axial: nz };
	const tools = { onHover: showProbe, onPick: pick, onWindowLevel: dragWindowLevel };
	views = [ ...document.querySelectorAll( '.view[data-axis]' ) ].map( ( root ) => {
		const axis = root.dataset.axis;
		return new SliceView( root, {
			volumeId, axis, count: counts[ axis ], index: Math.floor( counts[ axis ] / 2 ), display: { ...state },
			view: volume.views?.[ axis ], dims: volume.dims, tools,
			onIndex: ( index, view ) => {
				cross[ view.tools?.view.axis ?? 0 ] = index;
				drawCross();
			},
		} );
	} );
	cross = [ nx, ny, nz ].map( ( n ) => Math.floor( n / 2 ) );
	drawCross();
	const sagittal = document.querySelector( '.view[data-axis=sagittal] .frame' );
	// The server draws superior up; whether that is the last slice depends on
	// how the series was stacked (feet-to-head or head-to-feet).
	const vertical = volume.views?.sagittal?.vertical;
	range = new SliceRange( sagittal, {
		count: nz, start: 1, end: nz, topIsLast: vertical ? vertical.flipped !== false : true,
		onChange: ( s, e ) => {
			$( 'start-slice' ).value = s;
			$( 'end-slice' ).value = e;
			checkRegion( nz );
		},
	} );
	for ( const id of [ 'start-slice', 'end-slice' ] ) {
		$( id ).max = String( nz );
		$( id ).addEventListener( 'input', () => checkRegion( nz ) );
	}
	$( 'sample-rate' ).addEventListener( 'input', () => {
		showCheck( $( 'sample-rate' ), checkSampleRate( $( 'sample-rate' ).value ) );
		checkRegion( nz );
	} );
	$( 'start-slice' ).value = 1;
	$( 'end-slice' ).value = nz;
}

// The voxel the three views share (0-based [i, j, k]): each view is the slice through
// it and draws the other two as a cross-hair.
let cross = [ 0, 0, 0 ];

function drawCross() {
	for ( const view of views ) view.tools?.setCross( cross );
}

// A click on a view: the other views go to the slices through that voxel.
function pick( ijk, from ) {
	cross = ijk;
	for ( const view of views ) {
		if ( view.tools && view !== from.slice ) view.setIndex( ijk[ view.tools.view.axis ] );
	}
	drawCross();
	showProbe( ijk, from );
}

// Right-drag or Shift+drag: left–right widens the window, up–down raises the level,
// a pixel being a 500th of the volume's values.
function dragWindowLevel( dx, dy ) {
	const [ lo, hi ] = limits.range || [ 0, 500 ];
	const step = Math.max( hi - lo, 1 ) / 500;
	const round = ( v ) => Math.round( v * 100 ) / 100;
	state.window = round( Math.max( 1, state.window + dx * step ) );
	state.level = round( state.level - dy * step );
	$( 'window' ).value = state.window;
	$( 'level' ).value = state.level;
	$( 'wl-preset' ).value = '';
	refreshSlices( 120 );
}

// The readout under the pointer: the voxel's place at once (1-based, as the slice
// fields count), its value and label once the server answers; one question at a time,
// the newest asked next.
const probe = { wanted: null, tools: null, busy: false };

function showProbe( ijk, tools ) {
	if ( probe.tools && probe.tools !== tools ) probe.tools.probe.hidden = true;
	Object.assign( probe, { wanted: ijk, tools } );
	tools.probe.hidden = ! ijk;
	if ( ! ijk ) return;
	tools.probe.textContent = `${place( ijk )} · …`;
	askProbe();
}

function place( [ i, j, k ] ) {
	return `i ${i + 1}, j ${j + 1}, slice ${k + 1}`;
}

async function askProbe() {
	if ( probe.busy || ! probe.wanted ) return;
	const ijk = probe.wanted;
	probe.busy = true;
	try {
		const v = await api.voxel( volumeId, ijk );
		if ( probe.wanted === ijk ) {
			const value = Number.isInteger( v.value ) ? v.value : Number( v.value.toPrecision( 5 ) );
			const label = v.label ? ` · ${v.name || `label ${v.label}`}` : '';
			probe.tools.probe.textContent = `${place( ijk )} · ${value} ${v.units || limits.units}${label}`;
		}
	} catch ( err ) {
		if ( probe.wanted === ijk ) probe.tools.probe.textContent = `${place( ijk )} · ${err.message}`;
	} finally {
		probe.busy = false;
	}
	if ( probe.wanted !== ijk ) askProbe();
}

// The slice fields as typed, refused as the server would (never swapped nor clamped);
// the lines on the sagittal view follow only numbers that make a region.
function checkRegion( nz ) {
	const rate = parseSampleRate( $( 'sample-rate' ).value );
	const step = rate ? rate[ rate.length - 1 ] : 1;
	const bad = checkSlices( $( 'start-slice' ).value, $( 'end-slice' ).value, nz, step );
	showCheck( $( 'start-slice' ), bad?.field === 'start' ? bad.message : '' );
	showCheck( $( 'end-slice' ), bad?.field === 'end' ? bad.message : '' );
	if ( ! bad ) range.setRange( Number( $( 'start-slice' ).value ), Number( $( 'end-slice' ).value ) );
}

// Default colours of added structures: skin, bone, then a palette.
const STRUCTURE_COLORS = [ '#e8b89a', '#e9dfc8', '#c0504d', '#4f81bd', '#9bbb59', '#8064a2', '#f79646' ];

function structureRow( { level = '', name = '', color = '#e9dfc8', first = false } = {} ) {
	const remove = first ? el( 'span.muted', {}, 'threshold' ) : el( 'button.small', {
		type: 'button', title: 'Remove this structure', 'aria-label': 'Remove structure',
		onclick: ( e ) => e.target.closest( 'li' ).remove(),
	}, '×' );
	const levelInput = el( 'input.structure-level', {
		type: 'number', step: 'any', value: level, required: true, 'aria-label': 'Structure level', disabled: first,
		oninput: ( e ) => showCheck( e.target, checkLevel( e.target.value, limits.range, limits.units, 'Structure level' ) ),
	} );
	return el( 'li.structure-row.row', { dataset: first ? { first: '1' } : {} },
		el( 'input.structure-name', { type: 'text', value: name, placeholder: first ? 'name (optional)' : 'name', 'aria-label': 'Structure name' } ),
		levelInput,
		// Untouched colours stay the server's (skin, bone, soft tissue by level).
		el( 'input.structure-color', {
			type: 'color', value: color, 'aria-label': 'Structure colour', title: 'Colour (left as is: the server picks one by level)',
			oninput: ( e ) => { e.target.dataset.touched = '1'; },
		} ),
		remove );
}

function setupStructures() {
	const list = $( 'structure-list' );
	list.replaceChildren( structureRow( { level: state.threshold, first: true } ) );
	$( 'add-structure' ).addEventListener( 'click', () => {
		const n = list.children.length;
		list.append( structureRow( { color: STRUCTURE_COLORS[ ( n - 1 ) % STRUCTURE_COLORS.length ] } ) );
		list.lastElementChild.querySelector( '.structure-name' ).focus();
	} );
}

// [{level, name, color}]: the threshold first, then the added rows in order.
function structures() {
	return [ ...$( 'structure-list' ).children ].map( ( li ) => ( {
		level: li.dataset.first ? state.threshold : Number( li.querySelector( '.structure-level' ).value ),
		name: li.querySelector( '.structure-name' ).value.trim(),
		color: li.querySelector( '.structure-color' ).dataset.touched ? li.querySelector( '.structure-color' ).value : null,
		first: Boolean( li.dataset.first ),
	} ) );
}

// The form's inputs and the job fields (miss.spec) they fill.
const FORM_FIELDS = {
	components: 'components',
	min_size_mm3: 'min-size',
	start_slice: 'start-slice',
	end_slice: 'end-slice',
	sample_rate: 'sample-rate',
	decimate: 'decimate',
	error_bound: 'error-bound',
	reduce: 'reduce',
};

// Each input's default and range from the API's schema (GET /openapi.json), which the job's
// declaration makes: the page, the REST API and the command line default alike. The slice
// range's values come from the volume (setupViews).
function setupForm( schema ) {
	for ( const [ name, id ] of Object.entries( FORM_FIELDS ) ) {
		const field = schema.properties[ name ];
		const input = $( id );
		const range = field[ 'x-form' ] || {};
		if ( range.min != null ) input.min = range.min;
		if ( range.max != null ) input.max = range.max;
		if ( field.default != null ) input.value = [ field.default ].flat().join( ',' );
	}
}

// Windowed-sinc passes for "Smooth slice steps": on the MR head (0.41 × 0.41 × 1.5 mm) 15
// moved the skin 0.14 mm on average and 1.03 mm at most (10: 0.08 / 0.53; 20: 0.18 / 1.30),
// its volume by 0.02 %; the model's details show the figures of each model.
const SMOOTH_STEPS = 15;

// Slices much farther apart than the pixels leave stair steps across every surface (3D
// Slicer smooths its surfaces by default): on by default when the gap is over twice the
// pixel spacing, off for a nearly isotropic scan; the switch says why either way.
function setupSmoothing( volume ) {
	const [ sx, sy, sz ] = volume.spacing || [ 1, 1, 1 ];
	const gap = volume.slice_gap ?? sz;
	const pixel = Math.min( sx, sy );
	const steps = gap > 2 * pixel;
	$( 'smooth-steps' ).checked = steps;
	const mm = ( v ) => `${+v.toFixed( 2 )} mm`;
	$( 'smooth-hint' ).textContent = steps
		? `Slices ${mm( gap )} apart, pixels ${mm( pixel )}: light smoothing (${SMOOTH_STEPS} passes) takes away the steps; the model's details say how far it moved the surface.`
		: `Slices ${mm( gap )} apart, pixels ${mm( pixel )}: no steps to smooth away.`;
}

function sampleRate() {
	const parts = parseSampleRate( $( 'sample-rate' ).value ); // checked as typed
	return parts.length === 1 ? parts[ 0 ] : parts;
}

function modelParams( volume ) {
	const nz = volume.dims[ 2 ];
	const params = {
		volume: volumeId,
		level: state.threshold,
		sample_rate: sampleRate(),
		decimate: $( 'decimate' ).value,
		error_bound: Number( $( 'error-bound' ).value ),
		reduce: Number( $( 'reduce' ).value ),
	};
	const list = structures();
	if ( list.some( ( s ) => s.name || s.color ) ) {
		// Names and colours the user gave go to the server, which writes them into the model.
		delete params.level;
		params.parts = list.map( ( { level, name, color } ) => ( { level, ...( name && { name } ), ...( color && { color } ) } ) );
	} else if ( list.length > 1 ) {
		delete params.level;
		params.levels = list.map( ( s ) => s.level );
	}
	const labels = labelMap?.labels();
	if ( labels ) {
		params.labels = labels;
		if ( list.length <= 1 ) delete params.level; // the label parts alone, no threshold surface
	}
	if ( $( 'components' ).value !== 'all' ) params.components = $( 'components' ).value;
	// A label map's parts keep their own smoothing (the server's default for labels).
	if ( $( 'smooth-steps' ).checked && ! params.labels ) params.smooth = SMOOTH_STEPS;
	const minSize = Number( $( 'min-size' ).value );
	if ( minSize > 0 ) params.min_size_mm3 = minSize;
	// The whole stack is sent as no range at all, so it shares the cache with API clients that omit it.
	if ( range.start !== 1 || range.end !== nz ) {
		params.start_slice = range.start;
		params.end_slice = range.end;
	}
	return params;
}

// The model page's modules, loaded (fetched, compiled and run) once this page is ready,
// while the user chooses: Generate then shows the model's page in this document.
let modelPage = null;

function loadModelPage() {
	modelPage = import( './viewer-page.js' ).then( () => true, () => false );
}

// The model's page in this document (the address becomes the model's): its markup as the
// server sends it (GET /models/{id}, which records the view), this page's body replaced by
// it, its module run. A new page would first be loaded, parsed and started: 0.3-0.4 s of
// the first second on a desktop that draws in software. False (and nothing changed) when
// the markup or the modules cannot be had, or name other files than this page's (a new
// version of MISS since this page came): the caller goes to the page.
async function showModel( id ) {
	const path = urls.viewerPage( id );
	const page = new URL( './model-page.js', import.meta.url ).href;
	try {
		// The modules before the markup: without them the view is recorded once, by the
		// page the caller goes to.
		if ( ! modelPage || ! await modelPage ) return false;
		const response = await fetch( path );
		if ( ! response.ok || new URL( response.url ).pathname !== path ) return false;
		const doc = new DOMParser().parseFromString( await response.text(), 'text/html' );
		const script = doc.querySelector( 'body script[type=module]' );
		if ( ! script || new URL( script.getAttribute( 'src' ), location.href ).href !== page ) return false;
		script.remove();
		history.pushState( null, '', path );
		addEventListener( 'popstate', () => location.reload() ); // Back: the volume's page as it loads
		document.title = doc.title;
		document.body.replaceWith( document.adoptNode( doc.body ) );
		scrollTo( 0, 0 );
	} catch {
		return false;
	}
	// Marks the body the owner's and starts the page; should it not load after all, the
	// address is the model's already.
	import( page ).catch( () => location.reload() );
	return true;
}

// Generate shows the model's page at once: it shows the job's progress, draws a
// coarse preview within a second and then the model, while the rest is written.
async function generate( volume ) {
	showError( null );
	const inputs = [ ...document.querySelectorAll( '.side input' ) ];
	const bad = inputs.find( ( i ) => ! i.checkValidity() );
	if ( bad ) return void bad.reportValidity();
	const button = $( 'generate' );
	button.disabled = true;
	try {
		const job = await api.createModel( modelParams( volume ) );
		if ( ! await showModel( job.id ) ) location.assign( urls.viewerPage( job.id ) );
	} catch ( err ) {
		showError( err );
		loadModels();
		button.disabled = false;
	}
}

// One model of the list: its name (else its parameters), when it was made, and its
// state or size; a named model keeps its parameters as the link's tooltip.
function modelItem( m ) {
	const made = new Date( m.finished || m.created ).toLocaleString( [], { dateStyle: 'medium', timeStyle: 'short' } );
	const tail = m.status === 'done' ? `${formatCount( m.stats?.triangles )} △` : m.status;
	const link = el( 'a', { href: urls.viewerPage( m.id ), title: describeModel( m ) }, modelTitle( m ) );
	return el( 'li', { dataset: { id: m.id, status: m.status } },
		el( 'span.model-what', {}, link, el( 'span.muted.small-print', {}, made ) ),
		el( 'span.muted', {}, tail ) );
}

// Each model whose job is queued or running is followed (api.watchModel) and its entry
// redrawn as it changes, so it reads "done" when the job ends, without a reload.
const followed = new Set();

function followJob( m ) {
	if ( followed.has( m.id ) || m.status === 'done' || m.status === 'failed' ) return;
	followed.add( m.id );
	const redraw = ( now ) => document.querySelector( `#models li[data-id="${now.id}"]` )?.replaceWith( modelItem( now ) );
	watchModel( m.id, redraw ).catch( () => api.model( m.id ).then( redraw ) ).catch( () => {} )
		.finally( () => followed.delete( m.id ) );
}

async function loadModels() {
	try {
		const data = await api.models( volumeId );
		$( 'models' ).replaceChildren( ...( data.length ? data.map( modelItem ) : [ el( 'li.muted', {}, 'none yet' ) ] ) );
		data.forEach( followJob );
	} catch ( err ) {
		$( 'models' ).replaceChildren( el( 'li.muted', {}, err.message ) );
	}
}

async function main() {
	showSession();
	try {
		const [ volume, hist, form ] = await Promise.all( [ api.volume( volumeId ), api.histogram( volumeId ), api.modelForm() ] );
		setupForm( form );
		hist.bins = binEdges( hist );
		document.title = `MISS · ${volume.name}`;
		$( 'volume-name' ).textContent = volume.name;
		$( 'volume-meta' ).textContent = describeVolume( volume );
		setupWindowLevel( volume, hist );
		setupThreshold( hist, volume );
		setupViews( volume );
		setupStructures();
		setupSmoothing( volume );
		showPrivacy( $( 'privacy' ), volume );
		showNotes( $( 'volume-notes' ), volume );
		labelMap = new LabelMapPanel( $( 'labelmap' ), volume, showError, ( map ) => {
			state.labels = map;
			refreshSlices( 0 );
		} );
		$( 'generate' ).addEventListener( 'click', () => generate( volume ) );
		document.body.dataset.ready = '1';
		loadModels();
		if ( window.requestIdleCallback ) requestIdleCallback( loadModelPage, { timeout: 500 } );
		else setTimeout( loadModelPage, 0 );
	} catch ( err ) {
		showError( err );
	}
}

main();
