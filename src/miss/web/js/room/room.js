// The connection to a model's consultation room (WebSocket /ws/rooms/{model}).
// Messages are JSON; each server message is re-dispatched as an event of its
// type ('welcome', 'pin', 'chat' ...). The connection comes back by itself
// after a network drop, but not after a refusal the server meant (an expired
// link, a room one may not enter).

// Close codes after which reconnecting would only be refused again.
const FINAL = new Set( [ 1008, 4401, 4403, 4404, 4410 ] );

export class RoomClient extends EventTarget {
	// share: a share link's token (guests), name: a guest's display name.
	constructor( modelId, { share = '', name = '' } = {} ) {
		super();
		this.modelId = modelId;
		this.share = share;
		this.name = name;
		this.ws = null;
		this.retry = 500;
		this.closedForGood = false;
		this.timers = new Map();
	}

	url() {
		const q = new URLSearchParams();
		if ( this.share ) q.set( 'share', this.share );
		if ( this.name ) q.set( 'name', this.name );
		const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
		const query = q.toString();
		return `${scheme}://${location.host}/ws/rooms/${encodeURIComponent( this.modelId )}${query ? '?' + query : ''}`;
	}

	connect() {
		const ws = new WebSocket( this.url() );
		this.ws = ws;
		ws.onopen = () => {
			this.retry = 500;
			this.emit( 'open', {} );
		};
		ws.onmessage = ( event ) => {
			let message;
			try {
				message = JSON.parse( event.data );
			} catch ( err ) {
				return;
			}
			if ( message && typeof message.type === 'string' ) this.emit( message.type, message );
		};
		ws.onclose = ( event ) => {
			if ( this.ws !== ws ) return; // replaced by a reconnect
			this.closedForGood = FINAL.has( event.code );
			this.emit( 'closed', { code: event.code, reason: event.reason, final: this.closedForGood } );
			if ( ! this.closedForGood ) setTimeout( () => this.ws === ws && this.connect(), this.retry );
			this.retry = Math.min( this.retry * 2, 8000 );
		};
	}

	// Closes and opens again (a guest who changed their name).
	reconnect() {
		const old = this.ws;
		this.ws = null;
		old?.close( 1000 );
		this.connect();
	}

	emit( type, detail ) {
		this.dispatchEvent( new CustomEvent( type, { detail } ) );
	}

	on( type, fn ) {
		this.addEventListener( type, ( event ) => fn( event.detail ) );
	}

	get open() {
		return this.ws?.readyState === WebSocket.OPEN;
	}

	send( message ) {
		if ( this.open ) this.ws.send( JSON.stringify( message ) );
	}

	// At most one message of this kind per `ms`; the latest one always goes out
	// (a trailing send), so the last camera pose or pointer position arrives.
	throttled( kind, message, ms = 80 ) {
		const slot = this.timers.get( kind ) || { last: 0, timer: 0, pending: null };
		this.timers.set( kind, slot );
		const wait = slot.last + ms - performance.now();
		if ( wait <= 0 ) {
			// A trailing send still waiting (its timer late: the page was busy) holds an
			// older message; sent after this one it would undo it.
			clearTimeout( slot.timer );
			slot.timer = 0;
			slot.last = performance.now();
			this.send( message );
			return;
		}
		slot.pending = message;
		if ( ! slot.timer ) {
			slot.timer = setTimeout( () => {
				slot.timer = 0;
				slot.last = performance.now();
				this.send( slot.pending );
			}, wait );
		}
	}
}
