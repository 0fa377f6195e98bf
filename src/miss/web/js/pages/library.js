// Library page: the links colleagues shared with you, the list of volumes as cards
// (newest first, searchable), upload by picker or drag and drop, and (for an account
// that may use one) the From PACS tab.

import { showSession } from '../session.js';
import { api, urls } from '../api.js';
import { describeVolume, el, kindOf } from '../format.js';
import { keepOnly, rememberedLink } from '../shared-links.js';
import { droppedFiles, groupUploads, uploadLabel, uploadVolume } from '../upload.js';
import { setupPacs } from '../pacs-panel.js';

const $ = ( id ) => document.getElementById( id );

function showError( node, err ) {
	node.textContent = err ? err.message || String( err ) : '';
	node.hidden = ! err;
}

// "values -1500 … 2075 HU": whole numbers past 100 (a scanner's noise is no information).
function valueRange( volume ) {
	const value = ( v ) => Number.isInteger( v ) ? String( v ) : v.toFixed( Math.abs( v ) >= 100 ? 0 : 2 );
	const units = volume.units ? ` ${volume.units}` : '';
	return `values ${value( volume.range[ 0 ] )} … ${value( volume.range[ 1 ] )}${units}`;
}

function volumeCard( volume ) {
	const href = urls.volumePage( volume.id );
	const remove = async () => {
		if ( ! confirm( `Delete “${volume.name}” and its models?` ) ) return;
		try {
			await api.deleteVolume( volume.id );
			card.remove();
			$( 'empty' ).hidden = $( 'volumes' ).children.length > 0;
			filterCards();
		} catch ( err ) {
			showError( $( 'list-error' ), err );
		}
	};
	const words = [ volume.name, kindOf( volume ), volume.modality, volume.owner,
		...( volume.series || [] ).map( ( s ) => s.description ) ];
	const card = el( 'article.card.volume-card', { dataset: { id: volume.id, search: words.filter( Boolean ).join( ' ' ).toLowerCase() } },
		el( 'a.thumb', { href, 'aria-label': `Open ${volume.name}` },
			el( 'img', { src: urls.thumbnail( volume.id ), alt: '', loading: 'lazy' } ) ),
		el( 'div.body',
			el( 'a.name', { href }, volume.name || volume.id ),
			el( 'div.facts', describeVolume( volume ) ),
			volume.range ? el( 'div.facts', valueRange( volume ) ) : null,
			el( 'div.actions',
				el( 'a.button.small.primary', { href }, 'Open' ),
				el( 'button.small.danger', { type: 'button', onclick: remove }, 'Delete' ) ) ) );
	return card;
}

// Shows the cards whose name, kind, owner or series description hold every word typed.
function filterCards() {
	const words = $( 'volume-search' ).value.toLowerCase().split( /\s+/ ).filter( Boolean );
	const cards = [ ...$( 'volumes' ).children ];
	let shown = 0;
	for ( const card of cards ) {
		card.hidden = ! words.every( ( w ) => card.dataset.search.includes( w ) );
		shown += card.hidden ? 0 : 1;
	}
	const total = `${cards.length} volume${cards.length === 1 ? '' : 's'}`;
	$( 'volume-count' ).textContent = words.length ? `${shown} of ${total}` : cards.length ? total : '';
	$( 'no-match' ).hidden = ! ( words.length && cards.length && ! shown );
	$( 'no-match' ).textContent = `No volume matches “${$( 'volume-search' ).value.trim()}”.`;
}

function sharedItem( entry ) {
	const path = rememberedLink( entry.id );
	const opened = new Date( entry.opened ).toLocaleString( [], { dateStyle: 'medium', timeStyle: 'short' } );
	const name = path ? el( 'a.name', { href: path }, entry.name ) : el( 'span.name', entry.name );
	return el( 'li', { dataset: { id: entry.id } }, name,
		el( 'span.facts', `shared by ${entry.shared_by} · ${entry.allows.join( ', ' )} · opened ${opened}` ),
		path ? null : el( 'span.facts', 'open it from the message you were sent: this browser did not keep the link' ) );
}

async function refreshShared() {
	try {
		const entries = await api.sharedWithMe();
		keepOnly( entries.map( ( e ) => e.id ) );
		$( 'shared-list' ).replaceChildren( ...entries.map( sharedItem ) );
		$( 'shared-empty' ).hidden = entries.length > 0;
		$( 'shared-section' ).hidden = false;
	} catch ( err ) {
		showError( $( 'list-error' ), err );
	}
}

async function refresh() {
	try {
		const volumes = await api.volumes(); // newest first, as the server orders them
		$( 'volumes' ).replaceChildren( ...volumes.map( volumeCard ) );
		filterCards();
		$( 'empty' ).hidden = volumes.length > 0;
		showError( $( 'list-error' ), null );
	} catch ( err ) {
		showError( $( 'list-error' ), err );
	}
	await refreshShared();
	document.body.dataset.ready = '1'; // the lists are drawn (tests wait for this)
}

// An upload's failure: the server's plain sentence, and what the reader found
// behind "More" for whoever wants it (or is asked for it by support).
function showUploadError( err ) {
	const node = $( 'upload-error' );
	const technical = err?.body?.technical;
	node.replaceChildren( el( 'span.plain', err.message || String( err ) ) );
	if ( technical ) {
		node.append( el( 'details.more', el( 'summary', 'More' ), el( 'p.mono.technical', technical ) ) );
	}
	node.hidden = false;
}

// Several series in one upload: the server lists them (largest first); the
// person picks one and the same files go again with its UID.
function chooseSeries( series, label ) {
	const box = $( 'upload-choice' );
	return new Promise( ( resolve ) => {
		const options = series.map( ( s, i ) => el( 'label.series-option',
			el( 'input', { type: 'radio', name: 'series', value: s.uid, checked: i === 0 } ),
			el( 'span', [ s.modality || 'Scan', s.description || '(no description)',
				`${s.slices} slice${s.slices === 1 ? '' : 's'}`,
				s.dims?.length >= 2 ? `${s.dims[ 0 ]} × ${s.dims[ 1 ]}` : '' ].filter( Boolean ).join( ' · ' ) ) ) );
		const finish = ( uid ) => {
			box.hidden = true;
			box.replaceChildren();
			resolve( uid );
		};
		const read = el( 'button.primary', { type: 'submit' }, 'Read this series' );
		const cancel = el( 'button', { type: 'button', onclick: () => finish( null ) }, 'Cancel' );
		const form = el( 'form.series-choice',
			el( 'fieldset',
				el( 'legend', `${label} holds ${series.length} series: which one should MISS read?` ),
				...options ),
			el( 'div.row', read, cancel ) );
		form.addEventListener( 'submit', ( e ) => {
			e.preventDefault();
			finish( form.querySelector( 'input[name=series]:checked' )?.value || null );
		} );
		box.replaceChildren( form );
		box.hidden = false;
		read.focus();
	} );
}

// One upload (one file, or the several that make one scan), with its bar; a
// zip or folder of several series asks which one and sends it again.
async function uploadOne( files, label ) {
	const bar = $( 'upload-progress' );
	$( 'upload-state' ).hidden = false;
	$( 'upload-name' ).textContent = label;
	let fields = {};
	for ( ;; ) {
		bar.value = 0;
		bar.removeAttribute( 'data-done' );
		try {
			const volume = await uploadVolume( files, ( fraction, phase ) => {
				bar.value = fraction;
				$( 'upload-text' ).textContent = phase === 'reading' ? 'reading the scan…' : `${Math.round( fraction * 100 )} %`;
			}, fields );
			$( 'upload-text' ).textContent = 'done';
			bar.dataset.done = '1';
			$( 'volumes' ).prepend( volumeCard( volume ) );
			$( 'empty' ).hidden = true;
			filterCards();
			return;
		} catch ( err ) {
			const series = err?.status === 409 && err.body?.series;
			if ( Array.isArray( series ) && series.length > 1 && ! fields.series ) {
				$( 'upload-text' ).textContent = 'choose a series';
				const uid = await chooseSeries( series, label );
				if ( uid ) {
					fields = { series: uid };
					continue;
				}
				$( 'upload-text' ).textContent = 'cancelled';
				return;
			}
			$( 'upload-text' ).textContent = 'failed';
			showUploadError( err );
			return;
		}
	}
}

// Uploads go one after another: parallel ones would only compete for the
// same link and the same two server cores.
async function uploadAll( files, folder = '' ) {
	showError( $( 'upload-error' ), null );
	const { groups, refused } = groupUploads( files );
	if ( refused.length && ! groups.length ) {
		const names = refused.slice( 0, 3 ).join( ', ' ) + ( refused.length > 3 ? ', …' : '' );
		showError( $( 'upload-error' ), new Error( `${names}: not a scan MISS reads; choose DICOM files (or their folder or a .zip of them), NIfTI, NRRD or MetaImage` ) );
		return;
	}
	for ( const group of groups ) await uploadOne( group, uploadLabel( group, folder ) );
}

function setupUpload() {
	const zone = $( 'dropzone' );
	const input = $( 'file-input' );
	input.addEventListener( 'change', () => {
		uploadAll( [ ...input.files ] );
		input.value = '';
	} );
	// The whole window accepts a drop, so a near miss does not open the file in the tab.
	let depth = 0;
	window.addEventListener( 'dragenter', ( e ) => {
		e.preventDefault();
		depth ++;
		zone.classList.add( 'over' );
	} );
	window.addEventListener( 'dragleave', () => {
		depth = Math.max( 0, depth - 1 );
		if ( depth === 0 ) zone.classList.remove( 'over' );
	} );
	window.addEventListener( 'dragover', ( e ) => e.preventDefault() );
	window.addEventListener( 'drop', ( e ) => {
		e.preventDefault();
		depth = 0;
		zone.classList.remove( 'over' );
		droppedFiles( e.dataTransfer ).then( ( { files, folder } ) => {
			if ( files.length ) uploadAll( files, folder );
		} ).catch( ( err ) => showError( $( 'upload-error' ), err ) );
	} );
}

// A volume imported from the PACS joins the list as an upload does.
async function addVolume( id ) {
	try {
		const volume = await api.volume( id );
		$( 'volumes' ).querySelector( `[data-id="${CSS.escape( id )}"]` )?.remove();
		$( 'volumes' ).prepend( volumeCard( volume ) );
		$( 'empty' ).hidden = true;
		filterCards();
	} catch ( err ) {
		showError( $( 'list-error' ), err );
	}
}

showSession().then( ( me ) => setupPacs( me, { onImported: addVolume } ) );
setupUpload();
$( 'volume-search' ).addEventListener( 'input', filterCards );
refresh();
