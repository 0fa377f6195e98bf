// Library page: the list of volumes as cards, upload by picker or drag and drop, and
// (for an account that may use one) the From PACS tab.

import { showSession } from '../session.js';
import { api, urls } from '../api.js';
import { describeVolume, el } from '../format.js';
import { looksLikeVolume, uploadVolume } from '../upload.js';
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
		} catch ( err ) {
			showError( $( 'list-error' ), err );
		}
	};
	const card = el( 'article.card.volume-card', { dataset: { id: volume.id } },
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

async function refresh() {
	try {
		const volumes = await api.volumes();
		$( 'volumes' ).replaceChildren( ...volumes.map( volumeCard ) );
		$( 'empty' ).hidden = volumes.length > 0;
		showError( $( 'list-error' ), null );
	} catch ( err ) {
		showError( $( 'list-error' ), err );
	}
	document.body.dataset.ready = '1'; // the list is drawn (tests wait for this)
}

// Files go one after another: parallel uploads would only compete for the
// same link and the same two server cores.
async function uploadAll( files ) {
	const state = $( 'upload-state' );
	const bar = $( 'upload-progress' );
	showError( $( 'upload-error' ), null );
	for ( const file of files ) {
		if ( ! looksLikeVolume( file.name ) ) {
			showError( $( 'upload-error' ), new Error( `${file.name}: not a scan MISS reads; use a .zip of DICOM files, .nii, .nii.gz, .nrrd or .mha` ) );
			continue;
		}
		state.hidden = false;
		$( 'upload-name' ).textContent = file.name;
		bar.value = 0;
		bar.removeAttribute( 'data-done' );
		try {
			const volume = await uploadVolume( file, ( fraction, phase ) => {
				bar.value = fraction;
				$( 'upload-text' ).textContent = phase === 'reading' ? 'reading the scan…' : `${Math.round( fraction * 100 )} %`;
			} );
			$( 'upload-text' ).textContent = 'done';
			bar.dataset.done = '1';
			$( 'volumes' ).prepend( volumeCard( volume ) );
			$( 'empty' ).hidden = true;
		} catch ( err ) {
			$( 'upload-text' ).textContent = 'failed';
			showError( $( 'upload-error' ), new Error( `${file.name}: ${err.message}` ) );
		}
	}
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
		const files = [ ...( e.dataTransfer?.files || [] ) ];
		if ( files.length ) uploadAll( files );
	} );
}

// A volume imported from the PACS joins the list as an upload does.
async function addVolume( id ) {
	try {
		const volume = await api.volume( id );
		$( 'volumes' ).querySelector( `[data-id="${CSS.escape( id )}"]` )?.remove();
		$( 'volumes' ).prepend( volumeCard( volume ) );
		$( 'empty' ).hidden = true;
	} catch ( err ) {
		showError( $( 'list-error' ), err );
	}
}

showSession().then( ( me ) => setupPacs( me, { onImported: addVolume } ) );
setupUpload();
refresh();
