// The MISS REST API as small functions. Every failure becomes an ApiError whose
// message is the server's `detail`, because that text already says what to fix.
// The pages authenticate with the session cookie; every write echoes the CSRF
// cookie in X-CSRF-Token, and a 401 sends the browser to the login page.

export class ApiError extends Error {
	constructor( status, detail, body = null ) {
		super( detail );
		this.name = 'ApiError';
		this.status = status;
		this.body = body; // the whole answer: `technical`, the `series` to choose among
	}
}

// FastAPI sends `detail` as a string for our own errors and as a list of
// {loc, msg} for request validation errors; show both as one readable line.
export function detailText( body, status ) {
	const detail = body && body.detail;
	if ( typeof detail === 'string' ) return detail;
	if ( Array.isArray( detail ) ) {
		return detail.map( ( d ) => ( d.loc ? d.loc.filter( ( p ) => p !== 'body' ).join( '.' ) + ': ' : '' ) + d.msg ).join( '; ' );
	}
	return `request failed (HTTP ${status})`;
}

// The value the server wants back in X-CSRF-Token (a cookie the page may read,
// which another site's page cannot).
export function csrfToken() {
	const found = document.cookie.split( '; ' ).find( ( c ) => c.startsWith( 'miss_csrf=' ) );
	return found ? decodeURIComponent( found.slice( 'miss_csrf='.length ) ) : '';
}

export function loginUrl() {
	return `/login?next=${encodeURIComponent( location.pathname + location.search )}`;
}

// One request to the API, the way every page makes them: JSON in and out, or a
// FormData upload whose progress onProgress(fraction, phase) hears ('sending' while the
// bytes go out, 'reading' once they are all sent and the server reads them). XHR
// rather than fetch because only XHR reports upload progress. A 401 sends the browser
// to the login page unless `login: false` (share links, the login form itself).
export function request( method, path, body, { onProgress = null, login = true } = {} ) {
	const headers = { Accept: 'application/json' };
	if ( method !== 'GET' ) headers[ 'X-CSRF-Token' ] = csrfToken();
	let payload = body ?? null;
	if ( body !== undefined && ! ( body instanceof FormData ) ) {
		headers[ 'Content-Type' ] = 'application/json';
		payload = JSON.stringify( body );
	}
	return new Promise( ( resolve, reject ) => {
		const xhr = new XMLHttpRequest();
		xhr.open( method, path );
		for ( const [ name, value ] of Object.entries( headers ) ) xhr.setRequestHeader( name, value );
		if ( onProgress ) {
			xhr.upload.onprogress = ( event ) => {
				if ( event.lengthComputable ) onProgress( event.loaded / event.total, 'sending' );
			};
			xhr.upload.onload = () => onProgress( 1, 'reading' );
		}
		xhr.onload = () => {
			let data = null;
			try {
				data = xhr.responseText ? JSON.parse( xhr.responseText ) : null;
			} catch ( err ) {
				data = { detail: xhr.responseText };
			}
			if ( xhr.status === 401 && login ) location.assign( loginUrl() );
			if ( xhr.status >= 200 && xhr.status < 300 ) resolve( data );
			else reject( new ApiError( xhr.status, detailText( data, xhr.status ), data ) );
		};
		xhr.onerror = () => reject( new ApiError( 0, 'the MISS server cannot be reached; check the connection (is `miss serve` running?) and try again' ) );
		xhr.onabort = () => reject( new ApiError( 0, 'cancelled' ) );
		xhr.send( payload );
	} );
}

const enc = encodeURIComponent;

export const api = {
	volumes: () => request( 'GET', '/api/volumes' ),
	volume: ( id ) => request( 'GET', `/api/volumes/${enc( id )}` ),
	deleteVolume: ( id ) => request( 'DELETE', `/api/volumes/${enc( id )}` ),
	histogram: ( id ) => request( 'GET', `/api/volumes/${enc( id )}/histogram` ),
	// One voxel's value (volume units) and label; [i, j, k] 0-based.
	voxel: ( id, [ i, j, k ] ) => request( 'GET', `/api/volumes/${enc( id )}/voxel?i=${i}&j=${j}&k=${k}` ),
	models: ( volumeId ) => request( 'GET', `/api/models?volume=${enc( volumeId )}` ),
	model: ( id ) => request( 'GET', `/api/models/${enc( id )}` ),
	createModel: ( params ) => request( 'POST', '/api/models', params ),
	cancelModel: ( id ) => request( 'POST', `/api/models/${enc( id )}/cancel` ),
	renameModel: ( id, name ) => request( 'PATCH', `/api/models/${enc( id )}`, { name } ),
	deleteModel: ( id ) => request( 'DELETE', `/api/models/${enc( id )}` ),
	// The job form's fields (miss.spec) as the API's schema declares them: defaults, and
	// the range the page offers (`x-form`).
	modelForm: () => request( 'GET', '/openapi.json' ).then( ( doc ) => doc.components.schemas.ModelRequest ),
	identity: ( id ) => request( 'GET', `/api/volumes/${enc( id )}/identity` ),
	me: () => request( 'GET', '/api/auth/me' ),
	login: ( username, password, next = '/' ) => request( 'POST', '/api/auth/login', { username, password, next }, { login: false } ),
	logout: () => request( 'POST', '/api/auth/logout' ),
	shares: ( modelId ) => request( 'GET', `/api/shares?model=${enc( modelId )}` ),
	createShare: ( params ) => request( 'POST', '/api/shares', params ),
	revokeShare: ( id ) => request( 'DELETE', `/api/shares/${enc( id )}` ),
	sharedWithMe: () => request( 'GET', '/api/shared-with-me' ),
	roomSessions: ( modelId ) => request( 'GET', `/api/models/${enc( modelId )}/room/sessions` ),
	roomEvents: ( modelId, session ) => request( 'GET', `/api/models/${enc( modelId )}/room/events?session=${enc( session )}` ),
	// The PACS (only for accounts with the pacs permission; 404 for the others).
	pacsServers: () => request( 'GET', '/api/pacs' ),
	pacsStudies: ( filters ) => request( 'GET', `/api/pacs/studies?${new URLSearchParams( filters )}` ),
	pacsSeries: ( study ) => request( 'GET', `/api/pacs/studies/${enc( study )}/series` ),
	pacsImport: ( study, series ) => request( 'POST', '/api/pacs/import', { study, series, segmentation: 'auto' } ),
	pacsImportStatus: ( id ) => request( 'GET', `/api/pacs/imports/${enc( id )}` ),
	// The viewer has drawn a running job's model: the job goes on with its other work.
	modelShown: ( id ) => request( 'POST', `/api/models/${enc( id )}/shown` ),
	sendToPacs: ( modelId ) => request( 'POST', `/api/models/${enc( modelId )}/pacs`, {} ),
};

export const urls = {
	volumePage: ( id ) => `/volumes/${enc( id )}`,
	viewerPage: ( id ) => `/models/${enc( id )}`,
	thumbnail: ( id ) => `/api/volumes/${enc( id )}/thumbnail.png`,
	slice( id, axis, index, { window, level, threshold, labels } ) {
		const q = new URLSearchParams();
		if ( window != null ) q.set( 'window', String( window ) );
		if ( level != null ) q.set( 'level', String( level ) );
		if ( threshold != null ) q.set( 'threshold', String( threshold ) );
		if ( labels ) { // the label map's colours laid over; its hash: a new map, a new URL
			q.set( 'labels', 'true' );
			q.set( 'map', String( labels ).slice( 0, 16 ) );
		}
		return `/api/volumes/${enc( id )}/slices/${axis}/${index}.png?${q}`;
	},
	download: ( id, format ) => `/api/models/${enc( id )}/model.${format}`,
	events: ( id ) => `/api/models/${enc( id )}/events`,
};

const FINAL = new Set( [ 'done', 'failed' ] );

// Follows a model job until it is done or failed, calling onUpdate with each
// status JSON. Server-Sent Events give live stages; if the stream breaks (a
// proxy that buffers, a server restart) it falls back to polling, so the page
// never hangs on a finished job. draws: this page draws the model once it can, and says
// so (api.modelShown); the job holds back its other work until then.
export function watchModel( id, onUpdate, { draws = false } = {} ) {
	return new Promise( ( resolve, reject ) => {
		let finished = false;
		const finish = ( model ) => {
			finished = true;
			if ( model.status === 'failed' ) reject( new ApiError( 422, model.error || 'the model could not be built' ) );
			else resolve( model );
		};
		const handle = ( model ) => {
			if ( finished ) return;
			onUpdate( model );
			if ( FINAL.has( model.status ) ) finish( model );
		};

		const poll = async () => {
			while ( ! finished ) {
				try {
					handle( await api.model( id ) );
				} catch ( err ) {
					if ( err.status === 404 ) return reject( err );
				}
				if ( ! finished ) await new Promise( ( r ) => setTimeout( r, 1000 ) );
			}
		};

		if ( typeof EventSource === 'undefined' ) return void poll();
		const source = new EventSource( urls.events( id ) + ( draws ? '?draws=1' : '' ) );
		const onMessage = ( event ) => {
			try {
				handle( JSON.parse( event.data ) );
			} catch ( err ) {
				return; // a keep-alive or comment line; the next event carries the state
			}
			if ( finished ) source.close();
		};
		source.onmessage = onMessage;
		// Servers may name their events; listen to the likely names as well.
		for ( const name of [ 'status', 'progress', 'update', 'done', 'failed' ] ) source.addEventListener( name, onMessage );
		source.onerror = () => {
			source.close();
			if ( ! finished ) poll();
		};
	} );
}
