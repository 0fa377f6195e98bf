// Replays a past consultation for the model's owner: the room's record (events
// in order, with times) played back onto the viewer -- pins and measurements
// appear, the presenter's views are followed, chat and who came and went scroll
// by -- with long pauses shortened. The live room's annotations are hidden
// meanwhile and come back when the replay ends or is stopped.

import { api } from '../api.js';
import { Annotations, discard } from './annotations.js';
import { CameraFollower } from './follow.js';
import { el, fill } from '../format.js';
import { clock } from './room-panel.js';
import { status } from '../test-hooks.js';

const MAX_PAUSE_MS = 1500; // a long silence in the meeting is a short one in the replay
const SPEED = 2;

function describe( e ) {
	const d = e.data || {};
	switch ( e.kind ) {
		case 'join': return `${e.author} joined`;
		case 'leave': return `${e.author} left`;
		case 'rename': return `${d.from} is now ${d.to}`;
		case 'presenter': return d.on ? `${e.author} presents` : `${e.author} stopped presenting`;
		case 'pin': return `${e.author} pinned “${d.note || ''}”`;
		case 'measure': return `${e.author} measured ${d.mm?.toFixed( 1 )} mm`;
		case 'chat': return `${e.author}: ${d.text}`;
		case 'unpin': return `${e.author} removed a pin`;
		case 'unmeasure': return `${e.author} removed a measurement`;
		default: return null; // views are shown, not told
	}
}

export class Replay {
	constructor( viewer, modelId, container, live ) {
		this.viewer = viewer;
		this.modelId = modelId;
		this.container = container;
		this.live = live; // the Consultation, whose annotations step aside
		this.run = 0;
		status.replay = { playing: false, events: 0, shown: 0, pins: 0 };
	}

	async list() {
		const sessions = await api.roomSessions( this.modelId );
		// Sessions that had a conversation (the server leaves out page visits), newest
		// first, folded away: the model's own sections come first.
		const when = ( s ) => new Date( s.start ).toLocaleString( [], { dateStyle: 'short', timeStyle: 'short' } );
		fill( this.container,
			el( 'details#history-details', {},
				el( 'summary', {}, el( 'h2', {}, `Past consultations (${sessions.length})` ) ),
				sessions.length ? null : el( 'span.muted', {}, 'No consultation yet.' ),
				el( 'ul#sessions.share-list', {}, ...[ ...sessions ].reverse().map( ( s ) => el( 'li', { dataset: { session: s.session } },
					el( 'span', {}, `#${s.session} · ${when( s )}` ),
					el( 'span.muted.small-print', {}, `${s.people.join( ', ' )} · ${s.events} ${s.events === 1 ? 'event' : 'events'}` ),
					el( 'button.small', { type: 'button', 'aria-label': `Replay consultation #${s.session} of ${when( s )}`, onclick: () => this.play( s.session ) }, 'Replay' ) ) ) ) ),
			el( 'div.row', {}, el( 'button#replay-stop.small', { type: 'button', hidden: true, onclick: () => this.stop() }, 'Stop replay' ) ),
			el( 'div#replay-log.chat-log', { hidden: true } ) );
	}

	async play( session ) {
		this.stop();
		const run = ++ this.run;
		const events = await api.roomEvents( this.modelId, session );
		this.marks = new Annotations( this.viewer );
		this.follower = new CameraFollower( this.viewer );
		if ( this.live ) this.live.annotations.group.visible = false;
		this.container.querySelector( '#replay-stop' ).hidden = false;
		const log = this.container.querySelector( '#replay-log' );
		log.hidden = false;
		log.replaceChildren();
		Object.assign( status.replay, { playing: true, events: events.length, shown: 0, pins: 0 } );
		let last = events.length ? Date.parse( events[ 0 ].at ) : 0;
		for ( const e of events ) {
			const at = Date.parse( e.at );
			await new Promise( ( r ) => setTimeout( r, Math.min( at - last, MAX_PAUSE_MS ) / SPEED ) );
			last = at;
			if ( run !== this.run ) return;
			this.apply( e, log );
		}
		status.replay.playing = false;
	}

	apply( e, log ) {
		const item = { id: e.data.id ?? e.id, author: e.author, at: e.at, ...e.data };
		if ( e.kind === 'pin' ) this.marks.addPin( { ...item, id: e.id } );
		else if ( e.kind === 'unpin' ) this.marks.removePin( e.data.id );
		else if ( e.kind === 'measure' ) this.marks.addMeasurement( { ...item, id: e.id } );
		else if ( e.kind === 'unmeasure' ) this.marks.removeMeasurement( e.data.id );
		else if ( e.kind === 'view' ) this.follower.follow( e.data );
		const text = describe( e );
		if ( text ) {
			log.append( el( 'div.chat-line', {}, el( 'span.mono.muted', {}, clock( e.at ) + ' ' ), text ) );
			log.scrollTop = log.scrollHeight;
		}
		status.replay.shown ++;
		status.replay.pins = this.marks.pins.size;
	}

	stop() {
		this.run ++;
		this.follower?.stop();
		if ( this.marks ) discard( this.marks );
		this.marks = null;
		if ( this.live ) this.live.annotations.group.visible = true;
		const stop = this.container.querySelector( '#replay-stop' );
		if ( stop ) stop.hidden = true;
		if ( status.replay ) status.replay.playing = false;
		this.viewer.requestRender();
	}
}
