// The library's "From PACS" tab: search the hospital's PACS for studies, list a study's
// series, import one as a volume (de-identified by the server, as an upload is) and
// follow the import to its volume. Patient names and IDs are shown here only: they are
// the PACS's search results, and nothing built from them leaves this panel.

import { api, urls } from './api.js';
import { el, fill } from './format.js';

const $ = ( id ) => document.getElementById( id );
const POLL_MS = 500;
const COLUMNS = 6;

function showError( err ) {
	$( 'pacs-error' ).textContent = err ? err.message || String( err ) : '';
	$( 'pacs-error' ).hidden = ! err;
}

// "20240131" -> "2024-01-31"; anything else as the PACS sent it.
function formatDate( date ) {
	return /^\d{8}$/.test( date || '' ) ? `${date.slice( 0, 4 )}-${date.slice( 4, 6 )}-${date.slice( 6 )}` : date || '–';
}

// The import's state in a series row: stage and bar while it runs, "Open" when done,
// the error and "Try again" when it failed.
async function runImport( cell, study, series, onImported ) {
	const text = el( 'span.muted', 'starting…' );
	const bar = el( 'progress', { max: 1, value: 0, 'aria-label': `Import of series ${series.number ?? ''}` } );
	fill( cell, el( 'div.pacs-import', text, bar ) );
	const retry = ( err ) => fill( cell, el( 'div.pacs-import',
		el( 'span.notice.error', { role: 'alert' }, err.message || String( err ) ),
		el( 'button.small', { type: 'button', onclick: () => runImport( cell, study, series, onImported ) }, 'Try again' ) ) );
	let job;
	try {
		job = await api.pacsImport( study, series.series );
		while ( job.status === 'queued' || job.status === 'running' ) {
			text.textContent = job.status === 'queued' ? 'waiting…' : `${job.stage} · ${Math.round( job.progress * 100 )} %`;
			bar.value = job.progress;
			await new Promise( ( r ) => setTimeout( r, POLL_MS ) );
			job = await api.pacsImportStatus( job.id );
		}
	} catch ( err ) {
		return retry( err );
	}
	if ( job.status === 'failed' ) return retry( new Error( job.error ) );
	fill( cell, el( 'div.pacs-import', { dataset: { done: '1' } },
		el( 'span.ok', 'Imported' ),
		el( 'a.button.small.primary', { href: urls.volumePage( job.volume_id ) }, 'Open' ) ) );
	onImported( job.volume_id );
}

function seriesRow( study, series, onImported ) {
	const action = el( 'td.action' );
	if ( series.importable ) {
		action.append( el( 'button.small.primary', {
			type: 'button',
			'aria-label': `Import series ${series.number ?? ''} ${series.description || series.modality}`,
			onclick: () => runImport( action, study, series, onImported ),
		}, 'Import' ) );
	} else {
		action.append( el( 'span.muted', series.reason || 'not importable' ) );
	}
	return el( 'tr', { dataset: { series: series.series } },
		el( 'td', series.number ?? '' ),
		el( 'td', series.modality || '–' ),
		el( 'td.num', String( series.instances ) ),
		el( 'td', series.description || '', series.segmentation ? el( 'span.muted', ' (segmentation)' ) : null ),
		action );
}

// Opens (or closes) the row under a study that lists its series.
async function toggleSeries( row, study, onImported ) {
	const open = row.nextElementSibling?.classList.contains( 'pacs-series' ) ? row.nextElementSibling : null;
	const button = row.querySelector( 'button' );
	if ( open ) {
		open.remove();
		button.setAttribute( 'aria-expanded', 'false' );
		return;
	}
	const cell = el( 'td', { colspan: COLUMNS }, el( 'span.muted', 'Listing the series…' ) );
	row.after( el( 'tr.pacs-series', { dataset: { study: study.study } }, cell ) );
	button.setAttribute( 'aria-expanded', 'true' );
	try {
		const series = await api.pacsSeries( study.study );
		fill( cell, el( 'table.pacs-series-table',
			el( 'thead', el( 'tr',
				el( 'th', { scope: 'col' }, '#' ), el( 'th', { scope: 'col' }, 'Modality' ),
				el( 'th', { scope: 'col' }, 'Images' ), el( 'th', { scope: 'col' }, 'Description' ),
				el( 'th', { scope: 'col' }, '' ) ) ),
			el( 'tbody', series.map( ( s ) => seriesRow( study.study, s, onImported ) ) ) ) );
	} catch ( err ) {
		fill( cell, el( 'span.notice.error', { role: 'alert' }, err.message ) );
	}
}

function studyRow( study, onImported ) {
	const row = el( 'tr.pacs-study', { dataset: { study: study.study } } );
	const name = el( 'button.link', {
		type: 'button',
		'aria-expanded': 'false',
		title: 'List this study’s series',
		onclick: () => toggleSeries( row, study, onImported ),
	}, study.patient_name || '(no name)' );
	return fill( row,
		el( 'td', name ),
		el( 'td', study.patient_id || '–' ),
		el( 'td', formatDate( study.study_date ) ),
		el( 'td', study.description || '' ),
		el( 'td', ( study.modalities || [] ).join( ', ' ) ),
		el( 'td.num', String( study.series_count ) ) );
}

// Search with the form's filters (blank ones left out), one page at a time.
function setupSearch( onImported ) {
	const form = $( 'pacs-search' );
	const body = $( 'pacs-studies' ).querySelector( 'tbody' );
	let filters = {};
	let next = 0;
	const load = async ( more ) => {
		showError( null );
		$( 'pacs-status' ).textContent = 'Searching…';
		$( 'pacs-more' ).disabled = true;
		try {
			const page = await api.pacsStudies( { ...filters, offset: more ? next : 0 } );
			const rows = page.studies.map( ( s ) => studyRow( s, onImported ) );
			if ( more ) body.append( ...rows );
			else body.replaceChildren( ...rows );
			next = page.offset + page.studies.length;
			$( 'pacs-studies' ).hidden = body.children.length === 0;
			$( 'pacs-more' ).hidden = ! page.more;
			const found = body.querySelectorAll( 'tr.pacs-study' ).length;
			$( 'pacs-status' ).textContent = found ? `${found} ${found === 1 ? 'study' : 'studies'}${page.more ? ' so far' : ''}` : 'No study matches.';
		} catch ( err ) {
			$( 'pacs-status' ).textContent = '';
			showError( err );
		} finally {
			$( 'pacs-more' ).disabled = false;
		}
	};
	form.addEventListener( 'submit', ( e ) => {
		e.preventDefault();
		filters = Object.fromEntries( [ ...new FormData( form ) ].map( ( [ k, v ] ) => [ k, v.trim() ] ).filter( ( [ , v ] ) => v ) );
		load( false );
	} );
	$( 'pacs-more' ).addEventListener( 'click', () => load( true ) );
}

// Two tabs, with the arrow keys moving between them as in any tab list.
function setupTabs() {
	const tabs = [ $( 'tab-volumes' ), $( 'tab-pacs' ) ];
	const select = ( tab ) => {
		for ( const t of tabs ) {
			const on = t === tab;
			t.setAttribute( 'aria-selected', String( on ) );
			t.tabIndex = on ? 0 : - 1;
			$( t.getAttribute( 'aria-controls' ) ).hidden = ! on;
		}
	};
	for ( const [ i, tab ] of tabs.entries() ) {
		tab.addEventListener( 'click', () => select( tab ) );
		tab.addEventListener( 'keydown', ( e ) => {
			if ( e.key !== 'ArrowLeft' && e.key !== 'ArrowRight' ) return;
			const other = tabs[ ( i + 1 ) % tabs.length ];
			select( other );
			other.focus();
		} );
	}
	$( 'library-tabs' ).hidden = false;
}

// Shows the tab when the account may use a PACS and the server has one; otherwise
// nothing (GET /api/pacs answers 404 then).
export async function setupPacs( me, { onImported } ) {
	if ( ! me?.pacs ) return;
	let servers;
	try {
		servers = await api.pacsServers();
	} catch ( err ) {
		return;
	}
	if ( ! servers.length ) return;
	$( 'pacs-name' ).textContent = `on ${servers[ 0 ].name}`;
	setupTabs();
	setupSearch( onImported );
}
