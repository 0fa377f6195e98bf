// A model's page for its owner (model.html at /models/{id}): waits for the model
// if it is still being built, draws it in GLB or VRML mode, lists its statistics
// and downloads, opens the model's consultation room, the share dialog and the
// replay of past sessions.

import { api, urls, watchModel } from '../api.js';
import { Consultation } from '../room/consult.js';
import { percent, stageLabel } from '../job.js';
import { Replay } from '../room/replay.js';
import { showSession } from '../session.js';
import { ShareDialog } from '../share-dialog.js';
import { StructuresPanel } from '../viewer/structures-panel.js';
import { fillDownloads, fillStats, overlay, setupDisplay } from '../viewer/viewer-ui.js';
import { status } from '../test-hooks.js';
import { ModelViewer } from '../viewer/viewer.js';

const $ = ( id ) => document.getElementById( id );
const modelId = decodeURIComponent( location.pathname.split( '/' ).filter( Boolean ).pop() );

async function waitUntilBuilt( model ) {
	if ( model.status === 'done' ) return model;
	const update = ( m ) => overlay( `Building the model: ${stageLabel( m.status === 'queued' ? 'queued' : m.stage )}`, percent( m ), { progress: m.progress || 0, model: m } );
	update( model );
	return watchModel( modelId, update );
}

function showVolume( volume ) {
	$( 'volume-link' ).textContent = volume.name;
	$( 'volume-link' ).href = urls.volumePage( volume.id );
	document.title = `MISS · ${volume.name}`;
	$( 'burned-in' ).hidden = ! volume.burned_in_annotation;
	const dialog = new ShareDialog( modelId, { burnedIn: volume.burned_in_annotation } );
	$( 'share' ).addEventListener( 'click', () => dialog.open() );
}

export async function start() {
	showSession();
	const viewer = new ModelViewer( $( 'stage' ) );
	let consult = null;
	const structures = new StructuresPanel( viewer );
	const onLoaded = () => {
		structures.refresh();
		consult?.modelLoaded();
	};
	const display = setupDisplay( viewer, ( fmt ) => urls.download( modelId, fmt ), { onLoaded } );
	try {
		let model = await api.model( modelId );
		api.volume( model.volume ).then( showVolume ).catch( () => {} );
		model = await waitUntilBuilt( model );
		fillStats( model );
		structures.setStats( model.stats );
		fillDownloads( model.files );
		consult = new Consultation( { viewer, modelId, container: $( 'room' ) } );
		const replay = new Replay( viewer, modelId, $( 'history' ), consult );
		replay.list().catch( () => {} );
		await display( new URLSearchParams( location.search ).get( 'mode' ) );
	} catch ( err ) {
		overlay( 'This model cannot be shown', err.message || String( err ) );
		status.error = err.message || String( err );
	}
}
