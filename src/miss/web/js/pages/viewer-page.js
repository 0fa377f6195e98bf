// A model's page for its owner (model.html at /models/{id}): follows the job while
// the model is built (a preview first, then the model), draws it in GLB or VRML
// mode, lists its statistics and downloads, opens the model's consultation room,
// the share dialog and the replay of past sessions.

import { api, urls, watchModel } from '../api.js';
import { Consultation } from '../room/consult.js';
import { modelTitle, percent, stageLabel } from '../job.js';
import { Replay } from '../room/replay.js';
import { showNotes } from '../format.js';
import { showSession } from '../session.js';
import { ShareDialog } from '../share-dialog.js';
import { StructuresPanel } from '../viewer/structures-panel.js';
import { fillDownloads, fillStats, overlay, setupDisplay } from '../viewer/viewer-ui.js';
import { status } from '../test-hooks.js';
import { ModelViewer } from '../viewer/viewer.js';
import { VolumePanel } from '../viewer/volume-panel.js';
import { addressViews, linkCamera } from '../viewer/deep-link.js';
import { LinkedSlices } from '../viewer/linked-slices.js';

const $ = ( id ) => document.getElementById( id );
// The page's model, from its address when the page starts (the volume page may load this
// module before it shows the page: pages/volume-page.js).
let modelId = null;
// Whether its owner cancelled the job here (the job's stream then ends it as failed).
let cancelled = false;

// The job's events (api.watchModel), asked for as the page starts, with its row: a
// preview written while the page starts up is heard of as soon as the viewer can draw it.
// The page listens from then on (listen); the last event is kept until it does. A finished
// model's stream says so once and ends.
function events( id ) {
	const heard = { last: null, listener: null };
	heard.done = watchModel( id, ( m ) => {
		heard.last = m;
		heard.listener?.( m );
	}, { draws: true } );
	heard.done.catch( () => {} ); // awaited by follow
	heard.listen = ( listener ) => {
		heard.listener = listener;
		if ( heard.last ) listener( heard.last );
	};
	return heard;
}

// While the job runs: its progress, then its preview (a coarse GLB) as soon as there is
// one, then the model's own GLB as soon as it is written (a large model's levels of
// detail instead, written before it), the view kept as the user turned it; resolves
// with the finished model and whether the model is drawn already.
async function follow( viewer, model, heard ) {
	let drawn = null; // 'preview' | 'full': what is drawn or on its way
	let queue = Promise.resolve();
	const draw = ( m ) => {
		const url = m.lod || m.files?.glb?.url || m.preview;
		const kind = m.lod || m.files?.glb ? 'full' : 'preview';
		if ( ! url || drawn === 'full' || drawn === kind ) return;
		drawn = kind;
		queue = queue.then( async () => {
			if ( kind === 'preview' ) viewer.setCoarse( true );
			const mode = url === m.lod ? 'lod' : 'glb';
			const triangles = await viewer.load( url, mode, undefined, { keepView: status.drawn != null } );
			if ( kind === 'full' ) viewer.setCoarse( false ); // before the frame that draws it
			Object.assign( status, { drawn: kind, triangles } );
			$( 'overlay' ).hidden = true;
			// The job holds back its other formats and its error until the model is drawn
			// here (the server may share this machine's cores): tell it once it is.
			if ( kind === 'full' && m.status === 'running' ) {
				viewer.whenDrawn().then( () => api.modelShown( modelId ) ).catch( () => {} );
			}
		} ).catch( ( err ) => {
			if ( kind === 'full' ) {
				drawn = 'preview'; // the finished model draws it again
				viewer.setCoarse( false );
			}
			console.warn( `the ${kind} could not be drawn yet: ${err.message || err}` );
		} );
	};
	const update = ( m ) => {
		const stage = stageLabel( m.status === 'queued' ? 'queued' : m.stage );
		if ( status.drawn ) {
			$( 'building' ).hidden = false;
			$( 'building' ).textContent = `${status.drawn === 'preview' ? 'Preview · ' : ''}${stage} · ${percent( m )}`;
		} else {
			overlay( `Building the model: ${stage}`, percent( m ), { progress: m.progress || 0, model: m } );
		}
		draw( m );
	};
	update( model );
	heard.listen( update );
	try {
		model = await heard.done;
	} finally {
		$( 'building' ).hidden = true;
	}
	draw( model );
	await queue;
	return { model, drawn: status.drawn === 'full' };
}

// The owner's hand on the model: its name (in the crumb), Rename, Delete (once confirmed;
// then the volume's page), and Cancel while its job is queued or running.
function showName( model ) {
	$( 'model-name' ).textContent = modelTitle( model );
	$( 'name-input' ).value = model.name || '';
}

function manageError( err ) {
	$( 'manage-error' ).hidden = ! err;
	$( 'manage-error' ).textContent = err ? err.message || String( err ) : '';
}

function setupManage( model ) {
	showName( model );
	const form = $( 'rename-form' );
	$( 'rename' ).addEventListener( 'click', () => {
		form.hidden = ! form.hidden;
		if ( ! form.hidden ) $( 'name-input' ).focus();
	} );
	form.addEventListener( 'submit', async ( event ) => {
		event.preventDefault();
		try {
			showName( await api.renameModel( modelId, $( 'name-input' ).value ) );
			form.hidden = true;
			manageError( null );
		} catch ( err ) {
			manageError( err );
		}
	} );
	$( 'delete-model' ).addEventListener( 'click', async () => {
		if ( ! confirm( `Delete the model “${modelTitle( model )}”, its files and its share links? This cannot be undone.` ) ) return;
		try {
			await api.deleteModel( modelId );
			location.assign( urls.volumePage( model.volume ) );
		} catch ( err ) {
			manageError( err );
		}
	} );
}

// Shown while the job is queued or running; the job's stream then ends it as failed.
function offerCancel( model ) {
	const button = $( 'cancel-job' );
	button.hidden = model.status !== 'queued' && model.status !== 'running';
	button.onclick = async () => {
		button.disabled = true;
		cancelled = true; // the job's stream may tell its end before this answer comes
		try {
			await api.cancelModel( modelId );
		} catch ( err ) {
			cancelled = false;
			manageError( err );
			button.disabled = false;
		}
	};
}

function showVolume( volume ) {
	$( 'volume-link' ).textContent = volume.name;
	$( 'volume-link' ).href = urls.volumePage( volume.id );
	document.title = `MISS · ${volume.name}`;
	$( 'burned-in' ).hidden = ! volume.burned_in_annotation;
	showNotes( $( 'volume-notes' ), volume );
	const dialog = new ShareDialog( modelId, { burnedIn: volume.burned_in_annotation } );
	$( 'share' ).addEventListener( 'click', () => dialog.open() );
}

// "Send to PACS", for the volume's owner when the account may use a PACS and the server
// has one (the server answers 404 to anybody else, 422 for a volume that did not come
// from DICOM).
async function offerPacs( me, volume ) {
	if ( ! me?.pacs || volume.owner !== me.name ) return;
	const servers = await api.pacsServers().catch( () => [] );
	if ( ! servers.length ) return;
	const button = $( 'send-pacs' );
	const result = $( 'pacs-result' );
	button.hidden = false;
	button.addEventListener( 'click', async () => {
		button.disabled = true;
		result.hidden = false;
		result.classList.remove( 'error' );
		result.textContent = 'Sending to the PACS…';
		try {
			const sent = await api.sendToPacs( modelId );
			const n = sent.sop_instance_uids.length;
			result.textContent = `Sent to ${sent.pacs}: ${sent.description} (${n} instance${n === 1 ? '' : 's'})`;
			result.dataset.sent = '1';
			button.textContent = 'Sent to PACS'; // once: a second send would be a second series
		} catch ( err ) {
			result.classList.add( 'error' );
			result.textContent = err.message;
			button.disabled = false;
		}
	} );
}

export async function start() {
	modelId = decodeURIComponent( location.pathname.split( '/' ).filter( Boolean ).pop() );
	const asked = api.model( modelId ); // on its way while the viewer starts up
	asked.catch( () => {} ); // awaited below
	const heard = events( modelId );
	const me = showSession();
	const viewer = new ModelViewer( $( 'stage' ) );
	let consult = null;
	const structures = new StructuresPanel( viewer );
	const onLoaded = () => {
		structures.refresh();
		consult?.modelLoaded();
	};
	let lod = null; // the finished model's levels of detail, when it is large
	const urlOf = ( fmt ) => ( fmt === 'lod' ? lod : urls.download( modelId, fmt ) );
	const display = setupDisplay( viewer, urlOf, { onLoaded } );
	try {
		let model = await asked;
		setupManage( model );
		offerCancel( model );
		const volumePanel = new VolumePanel( viewer, `/api/volumes/${encodeURIComponent( model.volume )}/voxels` );
		const volumeView = addressViews().has( 'volume' );
		const slices = new LinkedSlices( viewer, volumePanel );
		const slicesShown = addressViews().has( 'slices' ) ? slices.show( true ) : null; // voxels while the model loads
		let onStage = null;
		const staged = new Promise( ( resolve ) => ( onStage = resolve ) );
		// Voxels, module and layer while the model loads: its first frame has the volume.
		const shown = volumeView ? volumePanel.show( true, staged ) : null;
		const volume = api.volume( model.volume );
		volume.then( showVolume ).catch( () => {} );
		let drawn = false;
		if ( model.status !== 'done' ) {
			try {
				( { model, drawn } = await follow( viewer, model, heard ) );
			} finally {
				$( 'cancel-job' ).hidden = true;
			}
		}
		lod = model.lod;
		fillStats( model );
		structures.setStats( model.stats );
		fillDownloads( model.files );
		Promise.all( [ me, volume ] ).then( ( [ m, v ] ) => offerPacs( m, v ) ).catch( () => {} );
		consult = new Consultation( { viewer, modelId, container: $( 'room' ), structures, volume: volumePanel, slices } );
		const replay = new Replay( viewer, modelId, $( 'history' ), consult );
		replay.list().catch( () => {} );
		await display( new URLSearchParams( location.search ).get( 'mode' ), { drawn } );
		linkCamera( viewer ); // ?cam= in the address: this view, and the address follows it
		onStage();
		await Promise.all( [ shown, slicesShown ] );
	} catch ( err ) {
		overlay( cancelled ? 'Job cancelled' : 'This model cannot be shown', err.message || String( err ) );
		status.error = err.message || String( err );
	}
}
